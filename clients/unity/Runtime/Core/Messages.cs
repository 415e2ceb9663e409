// The EgoPose protocol v1 messages (PROTOCOL.md §5) as typed classes, encoded and decoded with MsgPack.cs.
//
// Client -> server: Hello, Hmd, Rgbd, SelectModel, Calibrate, GetBody, SetBody, ListModels, Ping.
// Server -> client: Welcome, Pose, Models, Error, SessionStatus, Calibration, Body, Pong.
// Each writes its fields in the order the server's own encoder does (type, v, then the table's order) and leaves
// absent optional fields out, so Encode(Decode(bytes)) gives back the golden fixtures byte for byte.
// Floats go on the wire as float32 (§2). Protocol.DecodeFromServer returns null for a message type this
// version does not know: a client must ignore it (§8, later v1 servers add types).
//
// Pure C#: no UnityEngine.
using System;
using System.Collections.Generic;

namespace EgoPose.Protocol
{
    /// <summary>A message the client cannot use: not msgpack, not a v1 map, or a field of the wrong type.</summary>
    public sealed class ProtocolException : Exception
    {
        public ProtocolException(string message) : base(message) { }
    }

    /// <summary>Any v1 message.</summary>
    public abstract class Message
    {
        public const int Version = 1;

        /// <summary>The message's <c>type</c> field.</summary>
        public abstract string Type { get; }

        /// <summary>The fields after <c>type</c> and <c>v</c>, in wire order.</summary>
        protected abstract void WriteFields(MsgMap map);

        public MsgMap ToMap()
        {
            var map = new MsgMap().Add("type", Type).Add("v", (long)Version);
            WriteFields(map);
            return map;
        }

        public byte[] Encode() { return MsgPack.Encode(ToMap()); }
    }

    // ------------------------------------------------------------------------------------- client -> server

    public sealed class Hello : Message
    {
        public string Role = "input"; // "input" (the headset) or "render" (viewers)
        public string Session;
        public string Model; // optional
        public string Token; // optional
        public string Client; // optional, free text for the server's logs

        public override string Type { get { return "hello"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("role", Role).Add("session", Session);
            Fields.AddIfSet(map, "model", Model);
            Fields.AddIfSet(map, "token", Token);
            Fields.AddIfSet(map, "client", Client);
        }
    }

    /// <summary>One headset sample: three device poses [px, py, pz, qx, qy, qz, qw] in the protocol's frame (§3).</summary>
    public sealed class Hmd : Message
    {
        public long Seq;
        public long TUs;
        public float[] Head = new float[7];
        public float[] Left = new float[7];
        public float[] Right = new float[7];
        public bool[] Valid = { true, true, true };
        public float[] Truth; // optional, recorded sessions only: 66 true joint coordinates (m)

        public override string Type { get { return "hmd"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("seq", Seq).Add("t_us", TUs);
            map.Add("head", Fields.Checked(Head, 7, "hmd.head")).Add("left", Fields.Checked(Left, 7, "hmd.left"));
            map.Add("right", Fields.Checked(Right, 7, "hmd.right"));
            if (Valid == null || Valid.Length != 3) throw new ArgumentException("hmd.valid must hold 3 flags");
            map.Add("valid", new List<object> { Valid[0], Valid[1], Valid[2] });
            if (Truth != null) map.Add("truth", Fields.Checked(Truth, 66, "hmd.truth"));
        }
    }

    /// <summary>One camera frame: a JPEG and a 16-bit millimetre PNG of the same size (§5 rgbd).</summary>
    public sealed class Rgbd : Message
    {
        public long Seq;
        public long TUs;
        public int Width;
        public int Height;
        public float[] Intrinsics = new float[4]; // fx, fy, cx, cy in pixels
        public byte[] Rgb;
        public byte[] Depth;
        public float[] CamFromHead; // optional row-major 4x4, head device -> camera (OpenCV axes)

        public override string Type { get { return "rgbd"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("seq", Seq).Add("t_us", TUs).Add("width", (long)Width).Add("height", (long)Height);
            map.Add("intrinsics", Fields.Checked(Intrinsics, 4, "rgbd.intrinsics"));
            map.Add("rgb", Rgb ?? new byte[0]).Add("depth", Depth ?? new byte[0]);
            if (CamFromHead != null) map.Add("cam_from_head", Fields.Checked(CamFromHead, 16, "rgbd.cam_from_head"));
        }
    }

    public sealed class SelectModel : Message
    {
        public string Model;

        public override string Type { get { return "select_model"; } }

        protected override void WriteFields(MsgMap map) { map.Add("model", Model); }
    }

    /// <summary>Ask the server to measure the wearer (§4.1): hold <see cref="Pose"/> still for <see cref="Seconds"/>.</summary>
    public sealed class Calibrate : Message
    {
        public string Pose = "tpose"; // "tpose" or "stand"
        public float Seconds = 2f; // 0.5 .. 10
        public bool Clear; // true: forget the session's calibration

        public override string Type { get { return "calibrate"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("pose", Pose).Add("seconds", Seconds).Add("clear", Clear);
        }
    }

    /// <summary>Ask for the wearer's body as the session knows it (§4.2); answered by <see cref="Body"/>.</summary>
    public sealed class GetBody : Message
    {
        public override string Type { get { return "get_body"; } }

        protected override void WriteFields(MsgMap map) { }
    }

    /// <summary>
    /// Serve a known wearer's body from the next hmd sample on (§4.2): <see cref="BoneLengthsM"/> as a
    /// <see cref="Body"/> gave them, or <see cref="Clear"/> to estimate the body again. Answered by <see cref="Body"/>.
    /// </summary>
    public sealed class SetBody : Message
    {
        public float[] BoneLengthsM; // 21, m: joints 1..21 (the §3 order), each from its parent; null with Clear
        public bool Clear;

        public override string Type { get { return "set_body"; } }

        protected override void WriteFields(MsgMap map)
        {
            if ((BoneLengthsM == null) != Clear)
                throw new ArgumentException("set_body: give BoneLengthsM or Clear, not both and not neither");
            if (BoneLengthsM != null) map.Add("bone_lengths_m", Fields.Checked(BoneLengthsM, Body.BoneCount, "set_body.bone_lengths_m"));
            map.Add("clear", Clear);
        }
    }

    public sealed class ListModels : Message
    {
        public override string Type { get { return "list_models"; } }

        protected override void WriteFields(MsgMap map) { }
    }

    public sealed class Ping : Message
    {
        public long? Nonce;
        public long? TUs;

        public override string Type { get { return "ping"; } }

        protected override void WriteFields(MsgMap map)
        {
            if (Nonce.HasValue) map.Add("nonce", Nonce.Value);
            if (TUs.HasValue) map.Add("t_us", TUs.Value);
        }
    }

    // ------------------------------------------------------------------------------------- server -> client

    public sealed class Welcome : Message
    {
        public string Session;
        public string Role;
        public string Server;
        public string Model;
        public List<string> Models = new List<string>();
        public string Provider; // optional: the onnxruntime execution provider running the active model

        public override string Type { get { return "welcome"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("session", Session).Add("role", Role).Add("server", Server).Add("model", Model);
            map.Add("models", Models.ConvertAll(name => (object)name));
            Fields.AddIfSet(map, "provider", Provider);
        }

        internal static Welcome Read(MsgMap map)
        {
            return new Welcome
            {
                Session = Fields.String(map, "session"),
                Role = Fields.String(map, "role"),
                Server = Fields.String(map, "server"),
                Model = Fields.String(map, "model"),
                Models = Fields.StringList(map, "models"),
                Provider = Fields.OptionalString(map, "provider"),
            };
        }
    }

    /// <summary>The body answering headset sample <see cref="Seq"/>: SMPL axis-angle rotations and joint positions.</summary>
    public sealed class Pose : Message
    {
        public const int JointCount = 22;
        public long Seq;
        public long TUs;
        public string Model;
        public float[] GlobalOrient = new float[3]; // pelvis axis-angle (rad), SMPL canonical frame -> world
        public float[] BodyPose = new float[63]; // joints 1..21, local axis-angle (rad)
        public float[] Transl = new float[3]; // world position of the pelvis joint (m)
        public float[] Joints = new float[66]; // world positions of the 22 joints (m)
        public MsgMap TimingUs = new MsgMap(); // stage name -> µs (long)
        public bool? Camera;
        public long? Skipped;
        public float[] Truth;
        public bool[] Planted; // optional (§planted-feet): left, right foot held planted on the floor; null: none planted by the model
        public float? FloorYM; // optional: world y (m) of the floor the served soles were held to

        public override string Type { get { return "pose"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("seq", Seq).Add("t_us", TUs).Add("model", Model);
            map.Add("global_orient", GlobalOrient).Add("body_pose", BodyPose).Add("transl", Transl);
            map.Add("joints", Joints).Add("timing_us", TimingUs);
            if (Camera.HasValue) map.Add("camera", Camera.Value);
            if (Skipped.HasValue) map.Add("skipped", Skipped.Value);
            if (Truth != null) map.Add("truth", Truth);
            if (Planted != null)
            {
                if (Planted.Length != 2) throw new ArgumentException("pose.planted must hold 2 flags");
                map.Add("planted", new List<object> { Planted[0], Planted[1] });
            }
            if (FloorYM.HasValue) map.Add("floor_y_m", FloorYM.Value);
        }

        internal static Pose Read(MsgMap map)
        {
            var timing = Fields.Get<MsgMap>(map, "timing_us");
            foreach (var stage in timing) Fields.Int(stage.Value, "pose.timing_us." + stage.Key);
            return new Pose
            {
                Seq = Fields.Int(map, "seq"),
                TUs = Fields.Int(map, "t_us"),
                Model = Fields.String(map, "model"),
                GlobalOrient = Fields.Floats(map, "global_orient", 3),
                BodyPose = Fields.Floats(map, "body_pose", 63),
                Transl = Fields.Floats(map, "transl", 3),
                Joints = Fields.Floats(map, "joints", 66),
                TimingUs = timing,
                Camera = Fields.OptionalBool(map, "camera"),
                Skipped = Fields.OptionalInt(map, "skipped"),
                Truth = map.Get("truth") == null ? null : Fields.Floats(map, "truth", 66),
                Planted = map.Get("planted") == null ? null : Fields.Bools(map, "planted", 2),
                FloorYM = Fields.OptionalFloat(map, "floor_y_m"),
            };
        }
    }

    public sealed class ModelInfo
    {
        public string Name;
        public List<string> Inputs = new List<string>(); // ⊆ {"hmd", "rgb", "depth"}
        public string Description;
        public string Sha256; // optional: the served model file's SHA-256, hex (§model-digests); null for code
        public string EncoderSha256; // optional: its visual encoder's, for models that read a camera
        // optional (§model-head-joint): where the model hangs the body's head joint, in the head device's frame
        // (x right, y up, z back; m); null from a server older than the field (assume 0, -0.024, 0.083)
        public float[] HeadJointM;
    }

    public sealed class Models : Message
    {
        public string Active;
        public List<ModelInfo> List = new List<ModelInfo>();

        public override string Type { get { return "models"; } }

        protected override void WriteFields(MsgMap map)
        {
            var items = new List<object>();
            foreach (var info in List)
            {
                var item = new MsgMap().Add("name", info.Name)
                    .Add("inputs", info.Inputs.ConvertAll(name => (object)name))
                    .Add("description", info.Description);
                Fields.AddIfSet(item, "sha256", info.Sha256);
                Fields.AddIfSet(item, "encoder_sha256", info.EncoderSha256);
                if (info.HeadJointM != null)
                {
                    if (info.HeadJointM.Length != 3) throw new ArgumentException("models.head_joint_m must hold 3 numbers");
                    item.Add("head_joint_m", info.HeadJointM);
                }
                items.Add(item);
            }
            map.Add("active", Active).Add("models", items);
        }

        internal static Models Read(MsgMap map)
        {
            var models = new Models { Active = Fields.String(map, "active") };
            foreach (object item in Fields.Get<List<object>>(map, "models"))
            {
                var info = item as MsgMap;
                if (info == null) throw new ProtocolException("models.models: expected maps");
                models.List.Add(new ModelInfo
                {
                    Name = Fields.String(info, "name"),
                    Inputs = Fields.StringList(info, "inputs"),
                    Description = Fields.String(info, "description"),
                    Sha256 = Fields.OptionalString(info, "sha256"),
                    EncoderSha256 = Fields.OptionalString(info, "encoder_sha256"),
                    HeadJointM = info.Get("head_joint_m") == null ? null : Fields.Floats(info, "head_joint_m", 3),
                });
            }
            return models;
        }
    }

    /// <summary>What went wrong (§6). <see cref="Fatal"/>: the server closes the connection next.</summary>
    public sealed class Error : Message
    {
        public string Code;
        public string Text; // the wire's "message"
        public bool Fatal;
        public long? Seq;
        public string RefType; // the type of the client message that caused it, when readable
        public long? RefSeq;

        public override string Type { get { return "error"; } }

        /// <summary>The server refused a body a client gave (§4.2): giving it again would be refused again.</summary>
        public bool RefusesBody { get { return RefType == "set_body" && Code == "out_of_range"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("code", Code).Add("message", Text).Add("fatal", Fatal);
            if (Seq.HasValue) map.Add("seq", Seq.Value);
            if (RefType != null)
            {
                var reference = new MsgMap().Add("type", RefType);
                if (RefSeq.HasValue) reference.Add("seq", RefSeq.Value);
                map.Add("ref", reference);
            }
        }

        internal static Error Read(MsgMap map)
        {
            var error = new Error
            {
                Code = Fields.String(map, "code"),
                Text = Fields.String(map, "message"),
                Fatal = Fields.Bool(map, "fatal"),
                Seq = Fields.OptionalInt(map, "seq"),
            };
            var reference = map.Get("ref") as MsgMap;
            if (reference != null)
            {
                error.RefType = Fields.String(reference, "type");
                error.RefSeq = Fields.OptionalInt(reference, "seq");
            }
            return error;
        }
    }

    /// <summary>To render clients: who is in the session (§4 session lifecycle).</summary>
    public sealed class SessionStatus : Message
    {
        public string Session;
        public string Event; // "joined", "input_joined", "input_left"
        public bool Input;
        public string Model;
        public long Renders;

        public override string Type { get { return "session"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("session", Session).Add("event", Event).Add("input", Input).Add("model", Model)
                .Add("renders", Renders);
        }

        internal static SessionStatus Read(MsgMap map)
        {
            return new SessionStatus
            {
                Session = Fields.String(map, "session"),
                Event = Fields.String(map, "event"),
                Input = Fields.Bool(map, "input"),
                Model = Fields.String(map, "model"),
                Renders = Fields.Int(map, "renders"),
            };
        }
    }

    /// <summary>Progress and result of a <see cref="Calibrate"/> request (§4.1), sent to every client.</summary>
    public sealed class Calibration : Message
    {
        public string Status; // "started", "done", "failed", "cleared"
        public string Pose;
        public string Text; // the wire's "message": for the user
        public float? HeadHeightM;
        public float? ArmSpanM;
        public float[] Corrections; // 12: head, left, right xyzw quaternions

        public override string Type { get { return "calibration"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("status", Status).Add("pose", Pose).Add("message", Text);
            if (HeadHeightM.HasValue) map.Add("head_height_m", HeadHeightM.Value);
            if (ArmSpanM.HasValue) map.Add("arm_span_m", ArmSpanM.Value);
            if (Corrections != null) map.Add("corrections", Corrections);
        }

        internal static Calibration Read(MsgMap map)
        {
            return new Calibration
            {
                Status = Fields.String(map, "status"),
                Pose = Fields.String(map, "pose"),
                Text = Fields.String(map, "message"),
                HeadHeightM = Fields.OptionalFloat(map, "head_height_m"),
                ArmSpanM = Fields.OptionalFloat(map, "arm_span_m"),
                Corrections = map.Get("corrections") == null ? null : Fields.Floats(map, "corrections", 12),
            };
        }
    }

    /// <summary>
    /// The wearer's body as the session knows it (§4.2), sent to every client after <see cref="GetBody"/> and
    /// <see cref="SetBody"/>. Keep a <see cref="Measured"/> one with the wearer's profile; give it back next time.
    /// </summary>
    public sealed class Body : Message
    {
        public const int BoneCount = 21;
        public float[] BoneLengthsM = new float[BoneCount]; // m: joints 1..21, each from its parent
        public bool Given; // a client gave it (set_body); otherwise the server's estimate
        public bool Measured; // the camera measured the wearer's bones and they stood (or calibrated)

        public override string Type { get { return "body"; } }

        protected override void WriteFields(MsgMap map)
        {
            map.Add("bone_lengths_m", BoneLengthsM).Add("given", Given).Add("measured", Measured);
        }

        internal static Body Read(MsgMap map)
        {
            return new Body
            {
                BoneLengthsM = Fields.Floats(map, "bone_lengths_m", BoneCount),
                Given = Fields.Bool(map, "given"),
                Measured = Fields.Bool(map, "measured"),
            };
        }
    }

    public sealed class Pong : Message
    {
        public long? Nonce;
        public long? TUs;
        public long ServerTUs;

        public override string Type { get { return "pong"; } }

        protected override void WriteFields(MsgMap map)
        {
            if (Nonce.HasValue) map.Add("nonce", Nonce.Value);
            if (TUs.HasValue) map.Add("t_us", TUs.Value);
            map.Add("server_t_us", ServerTUs);
        }

        internal static Pong Read(MsgMap map)
        {
            return new Pong
            {
                Nonce = Fields.OptionalInt(map, "nonce"),
                TUs = Fields.OptionalInt(map, "t_us"),
                ServerTUs = Fields.Int(map, "server_t_us"),
            };
        }
    }

    /// <summary>Entry points: encode any message, decode what the server sends.</summary>
    public static class Protocol
    {
        /// <summary>
        /// A server message, or null for a type this client does not know (ignore it, §8).
        /// Throws <see cref="ProtocolException"/> for bytes that are no v1 message.
        /// </summary>
        public static Message DecodeFromServer(byte[] data)
        {
            return DecodeFromServer(data, 0, data.Length);
        }

        public static Message DecodeFromServer(byte[] data, int offset, int count)
        {
            object value;
            try
            {
                value = MsgPack.Decode(data, offset, count);
            }
            catch (MsgPackException exc)
            {
                throw new ProtocolException("not one msgpack value: " + exc.Message);
            }
            var map = value as MsgMap;
            if (map == null) throw new ProtocolException("the message is not a msgpack map");
            string type = map.Get("type") as string;
            if (type == null) throw new ProtocolException("the message has no type string");
            if (!(map.Get("v") is long) || (long)map.Get("v") != Message.Version)
                throw new ProtocolException(type + ".v: expected " + Message.Version);
            switch (type)
            {
                case "welcome": return Welcome.Read(map);
                case "pose": return Pose.Read(map);
                case "models": return Models.Read(map);
                case "error": return Error.Read(map);
                case "session": return SessionStatus.Read(map);
                case "calibration": return Calibration.Read(map);
                case "body": return Body.Read(map);
                case "pong": return Pong.Read(map);
                default: return null;
            }
        }
    }

    /// <summary>Typed access to map fields; every mismatch names the field as PROTOCOL.md does.</summary>
    internal static class Fields
    {
        internal static void AddIfSet(MsgMap map, string key, string value)
        {
            if (value != null) map.Add(key, value);
        }

        internal static float[] Checked(float[] values, int length, string name)
        {
            if (values == null || values.Length != length)
                throw new ArgumentException(name + " must hold " + length + " floats");
            return values;
        }

        internal static T Get<T>(MsgMap map, string key) where T : class
        {
            var value = map.Get(key) as T;
            if (value == null) throw new ProtocolException(key + ": missing or of the wrong type");
            return value;
        }

        internal static string String(MsgMap map, string key) { return Get<string>(map, key); }

        internal static string OptionalString(MsgMap map, string key)
        {
            object value = map.Get(key);
            if (value != null && !(value is string)) throw new ProtocolException(key + ": expected a string");
            return (string)value;
        }

        internal static List<string> StringList(MsgMap map, string key)
        {
            var result = new List<string>();
            foreach (object item in Get<List<object>>(map, key))
            {
                var s = item as string;
                if (s == null) throw new ProtocolException(key + ": expected strings");
                result.Add(s);
            }
            return result;
        }

        internal static bool Bool(MsgMap map, string key)
        {
            object value = map.Get(key);
            if (!(value is bool)) throw new ProtocolException(key + ": expected a bool");
            return (bool)value;
        }

        internal static bool[] Bools(MsgMap map, string key, int length)
        {
            var items = Items(map, key, length);
            var result = new bool[length];
            for (int i = 0; i < length; i++)
            {
                if (!(items[i] is bool)) throw new ProtocolException(key + "[" + i + "]: expected a bool");
                result[i] = (bool)items[i];
            }
            return result;
        }

        /// <summary>An array field of exactly <paramref name="length"/> items.</summary>
        static List<object> Items(MsgMap map, string key, int length)
        {
            var items = Get<List<object>>(map, key);
            if (items.Count != length)
                throw new ProtocolException(key + ": expected exactly " + length + " items, got " + items.Count);
            return items;
        }

        internal static bool? OptionalBool(MsgMap map, string key)
        {
            return map.Get(key) == null ? (bool?)null : Bool(map, key);
        }

        internal static long Int(MsgMap map, string key) { return Int(map.Get(key), key); }

        internal static long Int(object value, string name)
        {
            if (!(value is long)) throw new ProtocolException(name + ": expected an integer");
            return (long)value;
        }

        internal static long? OptionalInt(MsgMap map, string key)
        {
            return map.Get(key) == null ? (long?)null : Int(map, key);
        }

        internal static float Float(object value, string name)
        {
            if (value is float) return (float)value;
            if (value is double) return (float)(double)value;
            if (value is long) return (long)value;
            throw new ProtocolException(name + ": expected a number");
        }

        internal static float? OptionalFloat(MsgMap map, string key)
        {
            object value = map.Get(key);
            return value == null ? (float?)null : Float(value, key);
        }

        internal static float[] Floats(MsgMap map, string key, int length)
        {
            var items = Items(map, key, length);
            var result = new float[length];
            for (int i = 0; i < length; i++) result[i] = Float(items[i], key + "[" + i + "]");
            return result;
        }
    }
}
