// Test program for the package's UnityEngine-free core (Runtime/Core), compiled with Mono by
// tests/clients/test_unity_core.py, which runs it in three modes and checks what it prints or writes:
//
//   golden GOLDEN_DIR OPENXR_DIR    every fixture decodes and re-encodes to the same bytes (generic and typed);
//                                   the client messages built from their fields give the fixtures' bytes
//   keeper                          BodyKeeper: what it asks, keeps, forgets, stores and reads back
//   convert IN.msgpack OUT.msgpack  frame conversions and SMPL retargeting on inputs from Python, results back
//   live URL SESSION RGB DEPTH      a session against a real server: hello, hmd at 90 Hz, rgbd at 30 Hz, poses
//                                   back, a render client seeing them, select_model, a malformed message, a kept
//                                   body given after the welcome, one out of range refused and forgotten
//   reconnect URL SESSION           the server goes away (after "up" is printed, until the test restarts it once
//                                   "down" is printed): the client comes back by itself, with its model and body
//
// Exit status 0: every check passed; otherwise the first failed check is printed.
using System;
using System.Collections.Generic;
using System.IO;
using System.Linq;
using System.Net.WebSockets;
using System.Threading;
using System.Threading.Tasks;
using EgoPose.Protocol;

static class CoreTests
{
    static int checks;

    static int Main(string[] args)
    {
        try
        {
            switch (args[0])
            {
                case "golden": Golden(args[1], args[2]); break;
                case "keeper": Keeper(); break;
                case "pins": Pins(); break;
                case "convert": Convert(args[1], args[2]); break;
                case "live": Live(args[1], args[2], args[3], args[4]); break;
                case "reconnect": Reconnect(args[1], args[2]); break;
                default: throw new ArgumentException("unknown mode " + args[0]);
            }
            Console.WriteLine("ok: " + checks + " checks");
            return 0;
        }
        catch (Exception exc)
        {
            Console.WriteLine("FAILED: " + exc);
            return 1;
        }
    }

    static void Check(bool condition, string what)
    {
        checks++;
        if (!condition) throw new Exception("check failed: " + what);
    }

    static void SameBytes(byte[] expected, byte[] actual, string what)
    {
        checks++;
        if (expected.SequenceEqual(actual)) return;
        int at = 0;
        while (at < Math.Min(expected.Length, actual.Length) && expected[at] == actual[at]) at++;
        throw new Exception(string.Format("{0}: bytes differ at offset {1} (expected {2} bytes, got {3})", what, at,
            expected.Length, actual.Length));
    }

    // ------------------------------------------------------------------------------------------------ golden
    static void Golden(string goldenDir, string openxrDir)
    {
        var files = Directory.GetFiles(goldenDir, "*.msgpack").Concat(Directory.GetFiles(openxrDir, "*.msgpack"));
        foreach (string path in files.OrderBy(p => p))
        {
            byte[] bytes = File.ReadAllBytes(path);
            string name = Path.GetFileName(path);
            SameBytes(bytes, MsgPack.Encode(MsgPack.Decode(bytes)), name + " generic round trip");
            var typed = Protocol.DecodeFromServer(bytes);
            if (typed != null) SameBytes(bytes, typed.Encode(), name + " typed round trip");
        }
        var golden = new Func<string, MsgMap>(n => (MsgMap)MsgPack.Decode(File.ReadAllBytes(Path.Combine(goldenDir, n + ".msgpack"))));
        foreach (var built in ClientExamples(golden))
            SameBytes(File.ReadAllBytes(Path.Combine(goldenDir, built.Key + ".msgpack")), built.Value.Encode(),
                built.Key + " built from fields");
        foreach (string serverType in new[] { "welcome", "pose", "models", "error", "session", "calibration", "body", "pong" })
            Check(Protocol.DecodeFromServer(File.ReadAllBytes(Path.Combine(goldenDir, serverType + ".msgpack"))) != null,
                serverType + " decodes as a server message");
        Check(Protocol.DecodeFromServer(MsgPack.Encode(new MsgMap().Add("type", "from_the_future").Add("v", 1L))) == null,
            "an unknown message type is ignored (null)");
        var pose = (Pose)Protocol.DecodeFromServer(File.ReadAllBytes(Path.Combine(goldenDir, "pose.msgpack")));
        Check(pose.Seq == 42 && pose.BodyPose[9] == 0.5f && pose.GlobalOrient[1] == 3.125f, "pose fields");
        Check(pose.Planted != null && pose.Planted[0] && !pose.Planted[1] && pose.FloorYM == 0f,
            "pose: which feet are planted and the floor (§planted-feet)");
        var error = (Error)Protocol.DecodeFromServer(File.ReadAllBytes(Path.Combine(goldenDir, "error.msgpack")));
        Check(error.Code == "wrong_length" && !error.Fatal && error.RefType == "hmd" && error.RefSeq == 43, "error fields");
        var models = (Models)Protocol.DecodeFromServer(File.ReadAllBytes(Path.Combine(goldenDir, "models.msgpack")));
        Func<string, string> Repeat = part => string.Concat(Enumerable.Repeat(part, 4));
        Check(models.Active == "egoposevr" && models.List.Count == 2
            && models.List[0].Sha256 == Repeat("0123456789abcdef") && models.List[0].EncoderSha256 == Repeat("fedcba9876543210")
            && models.List[1].Sha256 == null && models.List[1].EncoderSha256 == null, "models fields, digests where given");
        Check(models.List[0].HeadJointM != null && models.List[0].HeadJointM[0] == 0f
            && models.List[0].HeadJointM[1] == -0.0234375f && models.List[0].HeadJointM[2] == 0.0830078125f
            && models.List[1].HeadJointM == null, "models: the head joint where given (§model-head-joint)");
        var body = (Body)Protocol.DecodeFromServer(File.ReadAllBytes(Path.Combine(goldenDir, "body.msgpack")));
        Check(body.BoneLengthsM.SequenceEqual(ExampleBoneLengths()) && body.Given && !body.Measured, "body fields");
        SameBytes(MsgPack.Encode(new MsgMap().Add("type", "set_body").Add("v", 1L).Add("clear", true)),
            new SetBody { Clear = true }.Encode(), "set_body clear leaves the lengths out");
        MustRefuse(new byte[] { 0x81, 0xa4 }, "truncated");
        MustRefuse(new byte[] { 0xd4, 0x01, 0x02 }, "an extension type");
        MustRefuse(new byte[] { 0x81, 0x01, 0x02 }, "a non-string key");
        MustRefuse(new byte[] { 0x90, 0x90 }, "trailing bytes");
        MustRefuse(new byte[] { 0xdd, 0xff, 0xff, 0xff, 0xff }, "an array longer than the data");
        DamagedMessages(goldenDir);
    }

    /// <summary>Every golden server message damaged many ways (bytes changed, cut short, grown): each decodes or
    /// is a ProtocolException, never another exception (a cast, an index, an allocation).</summary>
    static void DamagedMessages(string goldenDir)
    {
        var random = new Random(12345);
        int refused = 0, read = 0;
        foreach (string serverType in new[] { "welcome", "pose", "models", "error", "session", "calibration", "body", "pong" })
        {
            byte[] golden = File.ReadAllBytes(Path.Combine(goldenDir, serverType + ".msgpack"));
            for (int trial = 0; trial < 3000; trial++)
            {
                var bytes = new List<byte>(golden);
                int kind = random.Next(3);
                if (kind == 0)
                    for (int k = 0; k <= random.Next(4); k++) bytes[random.Next(bytes.Count)] = (byte)random.Next(256);
                else if (kind == 1)
                {
                    int keep = random.Next(bytes.Count);
                    bytes.RemoveRange(keep, bytes.Count - keep);
                }
                else
                    bytes.InsertRange(random.Next(bytes.Count), Enumerable.Repeat((byte)random.Next(256), 1 + random.Next(8)));
                try
                {
                    Protocol.DecodeFromServer(bytes.ToArray());
                    read++;
                }
                catch (ProtocolException)
                {
                    refused++;
                }
                catch (Exception exc)
                {
                    throw new Exception(serverType + " damaged (trial " + trial + ") escaped as " + exc.GetType().Name + ": " + exc.Message);
                }
            }
        }
        Check(refused > 1000 && read > 100, "damaged messages: " + refused + " refused, " + read + " still read");
    }

    static void MustRefuse(byte[] bytes, string what)
    {
        checks++;
        try
        {
            Protocol.DecodeFromServer(bytes);
        }
        catch (ProtocolException)
        {
            return;
        }
        throw new Exception("accepted " + what);
    }

    /// <summary>The client messages of protocol/examples.py, built field by field as an app would.</summary>
    static Dictionary<string, Message> ClientExamples(Func<string, MsgMap> golden)
    {
        float half = 0.7071067690849304f;
        var rgbd = golden("rgbd");
        return new Dictionary<string, Message>
        {
            { "hello", new Hello { Role = "input", Session = "room-1", Model = "egoposevr", Token = "s3cret", Client = "unity/1.0" } },
            {
                "hmd", new Hmd
                {
                    Seq = 42, TUs = 1000000,
                    Head = new[] { 0f, 1.625f, 0f, 0f, 0f, 0f, 1f },
                    Left = new[] { -0.25f, 1f, -0.25f, 0f, 0f, 0f, 1f },
                    Right = new[] { 0.25f, 1f, -0.25f, 0f, half, 0f, half },
                    Valid = new[] { true, true, false },
                }
            },
            {
                "rgbd", new Rgbd
                {
                    Seq = 7, TUs = 1000500, Width = 4, Height = 2, Intrinsics = new[] { 2f, 2f, 2f, 1f },
                    Rgb = (byte[])rgbd.Get("rgb"), Depth = (byte[])rgbd.Get("depth"),
                    CamFromHead = new[] { 1f, 0f, 0f, 0f, 0f, 0f, 1f, 0.125f, 0f, -1f, 0f, -0.0625f, 0f, 0f, 0f, 1f },
                }
            },
            { "select_model", new SelectModel { Model = "hmd" } },
            { "list_models", new ListModels() },
            { "ping", new Ping { Nonce = 3, TUs = 1000900 } },
            { "calibrate", new Calibrate { Pose = "tpose", Seconds = 2f } },
            { "get_body", new GetBody() },
            { "set_body", new SetBody { BoneLengthsM = ExampleBoneLengths() } },
        };
    }

    /// <summary>protocol/examples.py's bone lengths: near the mean body's, in 1/16 m steps.</summary>
    static float[] ExampleBoneLengths()
    {
        return new[]
        {
            0.125f, 0.125f, 0.125f, 0.375f, 0.375f, 0.125f, 0.4375f, 0.4375f, 0.0625f, 0.125f, 0.125f, 0.1875f,
            0.125f, 0.125f, 0.125f, 0.125f, 0.125f, 0.25f, 0.25f, 0.25f, 0.25f,
        };
    }

    // ------------------------------------------------------------------------------------------------ keeper
    // FootPins (PROTOCOL.md §planted-feet): the two-bone reach puts the foot on a target within reach with the bones'
    // lengths kept and the knee bent on its own side, straightens towards one out of reach, and the pins follow
    // `planted`, a pause and a far hip.
    static void Pins()
    {
        var rng = new Random(3);
        Func<double, float> noise = scale => (float)((rng.NextDouble() * 2 - 1) * scale);
        for (int trial = 0; trial < 200; trial++)
        {
            var hip = new[] { noise(1), 1f + noise(0.1), noise(1) };
            var knee = new[] { hip[0] + noise(0.15), hip[1] - 0.42f + noise(0.05), hip[2] + noise(0.15) };
            var ankle = new[] { knee[0] + noise(0.2), knee[1] - 0.4f + noise(0.05), knee[2] + 0.1f + noise(0.1) };
            float thigh = Length(Minus(knee, hip)), shin = Length(Minus(ankle, knee));
            bool far = trial % 4 == 3;
            var way = Minus(ankle, hip);
            way = new[] { way[0] + noise(0.2), way[1], way[2] + noise(0.2) };
            float span = far ? thigh + shin + 0.3f : (float)(0.6 + 0.38 * rng.NextDouble()) * (thigh + shin);
            var target = Plus(hip, Times(way, span / Length(way))); // beyond thigh + shin, or within their reach
            float[] kneeTurn, thighTurn;
            FootPins.Reach(hip, knee, ankle, target, new[] { 0f, 0f, 1f }, out kneeTurn, out thighTurn);
            var newKnee = Plus(hip, FootPins.Rotate(thighTurn, Minus(knee, hip)));
            var shinNow = FootPins.Rotate(thighTurn, FootPins.Rotate(kneeTurn, Minus(ankle, knee)));
            var newAnkle = Plus(newKnee, shinNow);
            Check(Math.Abs(Length(Minus(newKnee, hip)) - thigh) < 1e-4 && Math.Abs(Length(shinNow) - shin) < 1e-4,
                "the reach keeps the bones' lengths");
            var bendBefore = Bend(hip, knee, ankle);
            var bendAfter = Bend(hip, newKnee, newAnkle);
            if (Length(bendBefore) > 0.12f && Length(bendAfter) > 0.02f) // farther off than the front's pull
                Check(Dot(bendBefore, FootPins.Rotate(thighTurn, bendBefore)) > 0 && Dot(FootPins.Rotate(thighTurn, bendBefore), bendAfter) > 0,
                    "the knee bends on the side it bent");
            if (!far)
                Check(Length(Minus(newAnkle, target)) < 1e-3, "a target within reach is reached (trial " + trial + ")");
            else
            {
                var along = Minus(target, hip);
                var reached = Minus(newAnkle, hip);
                Check(Math.Abs(Length(reached) - (thigh + shin)) < 2e-3
                      && Dot(reached, along) / (Length(reached) * Length(along)) > 0.9999f,
                    "a target out of reach straightens the leg towards it");
            }
        }

        foreach (float front in new[] { 1f, -1f })
        {
            float[] hip = { 0f, 1f, 0f }, knee = { 0f, 0.55f, 0.001f }, ankle = { 0f, 0.1f, 0f }, lower = { 0f, 0.25f, 0f };
            float[] kneeTurn, thighTurn;
            FootPins.Reach(hip, knee, ankle, lower, new[] { 0f, 0f, front }, out kneeTurn, out thighTurn);
            var bentKnee = Plus(hip, FootPins.Rotate(thighTurn, Minus(knee, hip)));
            Check(bentKnee[2] * front > 0.1f, "a straight leg whose hips come down bends its knee to the body's front");
        }

        var pins = new FootPins();
        float[] at = { 0.1f, 0.03f, 0.2f }, hip0 = { 0.1f, 0.9f, 0.1f };
        Check(pins.Target(0, true, 0, hip0, at, 0.85f) == null, "a foot that lands stays where the pose put it");
        Check(pins.Target(1, false, 0, hip0, at, 0.85f) == null, "a free foot has no pin");
        var moved = new[] { 0.3f, 0.03f, 0.2f };
        var pin = pins.Target(0, true, 11111, hip0, moved, 0.85f);
        Check(pin != null && pin.SequenceEqual(at), "while planted, the foot is held where it landed");
        Check(pins.Target(0, true, 22222, new[] { 5f, 0.9f, 0f }, moved, 0.85f) == null,
            "a pin out of the leg's reach (a recentred space) is dropped and the foot lands anew");
        Check(pins.Target(0, false, 33333, hip0, moved, 0.85f) == null, "a foot let go is free");
        pins.Target(0, true, 44444, hip0, at, 0.85f);
        Check(pins.Target(0, true, 44444 + FootPins.GapUs + 1, hip0, moved, 0.85f) == null,
            "after a pause the foot lands anew");
    }

    static float[] Minus(float[] a, float[] b) { return new[] { a[0] - b[0], a[1] - b[1], a[2] - b[2] }; }

    // Where the knee sits off the hip-to-ankle line: the way the leg bends.
    static float[] Bend(float[] hip, float[] knee, float[] ankle)
    {
        var line = Minus(ankle, hip);
        var off = Minus(knee, hip);
        return Minus(off, Times(line, Dot(off, line) / Dot(line, line)));
    }
    static float[] Plus(float[] a, float[] b) { return new[] { a[0] + b[0], a[1] + b[1], a[2] + b[2] }; }
    static float[] Times(float[] a, float s) { return new[] { a[0] * s, a[1] * s, a[2] * s }; }
    static float Dot(float[] a, float[] b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
    static float Length(float[] a) { return (float)Math.Sqrt(Dot(a, a)); }

    static void Keeper()
    {
        var lengths = ExampleBoneLengths();
        lengths[3] = 0.3912345f; // a length with many digits survives the text store exactly
        Check(BodyKeeper.Parse(BodyKeeper.Format(lengths)).SequenceEqual(lengths), "format and parse round trip");
        foreach (string damaged in new[] { null, "", "0.1,0.2", BodyKeeper.Format(lengths) + ",0.1",
                                           BodyKeeper.Format(lengths).Replace("0.125", "NaN"),
                                           BodyKeeper.Format(lengths).Replace("0.25", "-0.25"),
                                           BodyKeeper.Format(lengths).Replace("0.125", "x") })
            Check(BodyKeeper.Parse(damaged) == null, "damaged text reads as no body: " + damaged);

        var keeper = new BodyKeeper(null, 10.0);
        Check(keeper.Poll(0.0) is GetBody, "nothing kept: ask at once");
        Check(keeper.Poll(9.9) == null && keeper.Poll(10.0) is GetBody, "then every 10 s");
        Check(!keeper.Take(new Body { BoneLengthsM = lengths, Given = false, Measured = false }) && keeper.Kept == null,
            "an estimate the camera has not measured is not kept");
        Check(keeper.Take(new Body { BoneLengthsM = lengths, Given = false, Measured = true }), "a measured body is kept");
        Check(keeper.Kept.SequenceEqual(lengths), "its lengths");
        Check(!keeper.Take(new Body { BoneLengthsM = lengths, Given = false, Measured = true }), "the same body again: no change");
        Check(keeper.Poll(20.0) is GetBody, "the session still estimates: keep asking");
        var later = (float[])lengths.Clone();
        later[0] = 0.2f;
        Check(keeper.Take(new Body { BoneLengthsM = later, Given = false, Measured = true }) && keeper.Kept[0] == 0.2f,
            "a later measured estimate replaces it (the camera has seen more)");
        Check(!keeper.Take(new Body { BoneLengthsM = lengths, Given = true, Measured = true }) && keeper.Kept[0] == 0.2f,
            "a body some client gave is not kept as measured");
        Check(keeper.Poll(100.0) == null, "the session serves a given body: nothing to ask");
        Check(!keeper.Take(new Error { Code = "out_of_range", RefType = "calibrate" }), "another request's refusal");
        Check(keeper.Take(new Error { Code = "out_of_range", RefType = "set_body" }) && keeper.Kept == null,
            "a kept body the server refuses is forgotten");

        keeper = new BodyKeeper(lengths, 10.0);
        keeper.Poll(0.0);
        keeper.Take(new Body { BoneLengthsM = lengths, Given = true, Measured = true }); // given after the welcome
        Check(keeper.Poll(20.0) == null, "a kept body the session serves: nothing to ask");
        var clear = keeper.Forget();
        Check(clear.Clear && clear.BoneLengthsM == null && keeper.Kept == null, "forget: set_body clear");
        Check(keeper.Poll(0.5) is GetBody, "forgotten: ask again at once");
        MustThrow(() => new BodyKeeper(new float[20]), "a kept body of 20 lengths");
        MustThrow(() => new SetBody().Encode(), "set_body with neither lengths nor clear");
        MustThrow(() => new SetBody { BoneLengthsM = lengths, Clear = true }.Encode(), "set_body with both");
        MustThrow(() => new EgoPoseConnection(new ConnectionOptions { Body = new float[3] }), "a connection given 3 lengths");
    }

    static void MustThrow(Action action, string what)
    {
        checks++;
        try
        {
            action();
        }
        catch (ArgumentException)
        {
            return;
        }
        throw new Exception("accepted " + what);
    }

    // ----------------------------------------------------------------------------------------------- convert
    static void Convert(string inPath, string outPath)
    {
        var input = (MsgMap)MsgPack.Decode(File.ReadAllBytes(inPath));
        var output = new MsgMap();
        var openxr = new MsgMap();
        foreach (var case_ in (MsgMap)input.Get("openxr"))
        {
            var devices = (List<object>)case_.Value;
            var hmd = Frames.HmdFromUnity(7, 2000000, Device(devices[0]), Device(devices[1]), Device(devices[2]));
            openxr.Add(case_.Key, hmd.Encode());
        }
        output.Add("openxr", openxr);
        var tpose = Floats(input.Get("tpose_world"));
        var world = new List<object>();
        var avatar = new List<object>();
        var hips = new List<object>();
        foreach (object item in (List<object>)input.Get("poses"))
        {
            var pose = (MsgMap)item;
            var w = SmplRetarget.WorldRotations(Floats(pose.Get("global_orient")), Floats(pose.Get("body_pose")));
            world.Add(w);
            avatar.Add(SmplRetarget.AvatarWorldRotations(w, tpose));
            hips.Add(SmplRetarget.HipsPosition(Floats(pose.Get("transl")), 0.9f));
        }
        output.Add("world", world).Add("avatar", avatar).Add("hips", hips);
        File.WriteAllBytes(outPath, MsgPack.Encode(output));
    }

    static UnityDevicePose Device(object item)
    {
        var map = (MsgMap)item;
        return new UnityDevicePose(Floats(map.Get("position")), Floats(map.Get("rotation")), (int)(long)map.Get("state"));
    }

    static float[] Floats(object list)
    {
        return ((List<object>)list).Select(v => v is double ? (float)(double)v : (float)v).ToArray();
    }

    // -------------------------------------------------------------------------------------------------- live
    static void Live(string url, string session, string rgbPath, string depthPath)
    {
        var kept = ExampleBoneLengths(); // the wearer's body, kept from an earlier session
        var input = new EgoPoseConnection(new ConnectionOptions { Url = url, Session = session, Model = "egoposevr", Body = kept });
        var render = new EgoPoseConnection(new ConnectionOptions { Url = url, Session = session, Role = "render" });
        input.Start();
        WaitFor(() => input.State == ConnectionState.Open, "the input client is welcomed");
        Check(input.Welcome.Session == session && input.Welcome.Role == "input" && input.Welcome.Model == "egoposevr",
            "welcome names the session, the role and the model");
        var given = WaitForMessage<Body>(input, m => m.Given, "body answers the set_body sent after the welcome");
        Check(MaxDifference(given.BoneLengthsM, kept) < 1e-6, "the session serves the kept body");
        render.Start();
        WaitFor(() => render.State == ConnectionState.Open, "the render client is welcomed");
        var joined = WaitForMessage<SessionStatus>(render, m => m.Event == "joined", "the render client's session message");
        Check(joined.Input, "the render client sees the input client");

        byte[] rgb = File.ReadAllBytes(rgbPath), depth = File.ReadAllBytes(depthPath);
        var sent = StreamHeadset(input, rgb, depth, 90, 0, 90);
        // The newest sample is always answered; older ones may be skipped when the machine is busy (§newest-wins).
        WaitFor(() => input.LatestPose != null && input.LatestPose.Seq == 89, "the last headset sample is answered");
        Pose pose;
        Check(input.TryTakePose(out pose), "a pose is waiting");
        Check(sent.ContainsKey(pose.Seq) && pose.TUs == sent[pose.Seq], "pose.seq and t_us answer an hmd");
        Check(pose.GlobalOrient.Length == 3 && pose.BodyPose.Length == 63 && pose.Transl.Length == 3
              && pose.Joints.Length == 66, "pose shapes");
        Check(pose.Model == "egoposevr", "the session's model answers");
        Check(MaxDifference(BoneLengths(pose.Joints), kept) < 2e-3, "the served skeleton has the kept body's bones");
        // A busy server answers the samples that come before it has read the session's first frame without
        // it (§frames: a sample never waits for a frame), so keep streaming, as a headset does, until one used it.
        int next = 90;
        for (int tries = 0; pose.Camera != true && tries < 10; tries++, next += 30)
        {
            StreamHeadset(input, rgb, depth, 90, next, 30);
            long last = next + 29;
            WaitFor(() => input.LatestPose != null && input.LatestPose.Seq == last, "sample " + last + " is answered");
            Check(input.TryTakePose(out pose), "a pose is waiting");
        }
        Check(pose.Camera == true, "the fusion model used the camera");
        Check(!input.TryTakePose(out pose), "a pose is taken once");
        long lastSent = next - 1;
        WaitFor(() => render.LatestPose != null && render.LatestPose.Seq == lastSent, "the render client receives the poses");
        Check(render.PosesReceived == input.PosesReceived, "the render client receives every pose the input client does");

        input.Send(new SelectModel { Model = "hmd" });
        var listed = WaitForMessage<Models>(input, m => m.Active == "hmd", "models answers select_model");
        var fusion = listed.List.Find(info => info.Name == "egoposevr");
        Check(fusion != null && fusion.Sha256 != null && fusion.Sha256.Length == 64 && fusion.EncoderSha256 != null,
            "each model names the files it serves (§model-digests)");
        Check(listed.List.TrueForAll(info => info.HeadJointM != null && Math.Abs(info.HeadJointM[2] - 0.083f) < 1e-6f),
            "each model says where it hangs the head joint (§model-head-joint)");
        Check(listed.List.Find(info => info.Name == "procedural").Sha256 == null, "a model that is code names none");
        WaitForMessage<Models>(render, m => m.Active == "hmd", "the render client hears of the switch");
        StreamHeadset(input, rgb, depth, 90, next, 30);
        long afterSwitch = next + 29;
        WaitFor(() => input.TryTakePose(out pose) && pose.Seq == afterSwitch, "poses after the switch");
        Check(pose.Model == "hmd", "poses come from the new model");

        MalformedMessage(url, session);
        RefusedBody(url, session + "-giant", kept);
        input.Send(new Ping { Nonce = 77 });
        WaitForMessage<Pong>(input, m => m.Nonce == 77, "the input client still answers pings");
        Check(input.Reconnects == 0 && input.DroppedSends == 0, "no reconnects and nothing dropped");
        render.Dispose();
        input.Dispose();
        Console.WriteLine("poses: input " + input.PosesReceived + ", render " + render.PosesReceived);
    }

    /// <summary>A kept body the server refuses (a 1 m shin): out_of_range, and the connection stops giving it.</summary>
    static void RefusedBody(string url, string session, float[] kept)
    {
        var giant = (float[])kept.Clone();
        giant[4] = 1.0f; // within the wire's range (§5), not a body's (§4.2)
        var input = new EgoPoseConnection(new ConnectionOptions { Url = url, Session = session, Body = giant });
        input.Start();
        var error = WaitForMessage<Error>(input, m => m.RefType == "set_body", "the server refuses the body");
        Check(error.Code == "out_of_range" && !error.Fatal, "out_of_range, not fatal");
        WaitFor(() => input.BodyGivenOnConnect == null, "the refused body is no longer given");
        input.Send(new GetBody());
        Check(!WaitForMessage<Body>(input, m => true, "body answers get_body").Given, "the session estimates the body");
        input.Dispose();
    }

    static float[] BoneLengths(float[] joints)
    {
        var lengths = new float[Body.BoneCount];
        for (int j = 1; j <= lengths.Length; j++)
        {
            int p = SmplRetarget.Parents[j];
            double dx = joints[3 * j] - joints[3 * p], dy = joints[3 * j + 1] - joints[3 * p + 1], dz = joints[3 * j + 2] - joints[3 * p + 2];
            lengths[j - 1] = (float)Math.Sqrt(dx * dx + dy * dy + dz * dz);
        }
        return lengths;
    }

    static double MaxDifference(float[] a, float[] b)
    {
        return a.Zip(b, (x, y) => (double)Math.Abs(x - y)).Max();
    }

    static void Reconnect(string url, string session)
    {
        var kept = ExampleBoneLengths();
        var input = new EgoPoseConnection(new ConnectionOptions
        {
            Url = url, Session = session, MinBackoff = TimeSpan.FromMilliseconds(50), MaxBackoff = TimeSpan.FromMilliseconds(400),
            Body = kept,
        });
        input.Start();
        WaitFor(() => input.State == ConnectionState.Open, "the input client is welcomed");
        WaitForMessage<Body>(input, m => m.Given, "the kept body is given after the welcome");
        input.Send(new SelectModel { Model = "hmd" });
        WaitForMessage<Models>(input, m => m.Active == "hmd", "models answers select_model");
        StreamHeadset(input, new byte[0], new byte[0], 90, 0, 9);
        Pose pose = null;
        WaitFor(() => input.TryTakePose(out pose), "a pose");
        Console.WriteLine("up");
        WaitFor(() => input.State == ConnectionState.Waiting, "the client notices the server is gone");
        Check(!input.Send(new Hmd { Seq = 100, TUs = 5000000 }), "hmd is refused while the connection is down");
        Console.WriteLine("down");
        WaitFor(() => input.State == ConnectionState.Open, "the client reconnects by itself");
        Check(input.Welcome.Model == "hmd", "the new session resumes the model");
        var given = WaitForMessage<Body>(input, m => m.Given, "the kept body is given to the new server's session");
        Check(MaxDifference(given.BoneLengthsM, kept) < 1e-6, "the same body");
        Check(input.Reconnects >= 1 && input.DroppedSends == 1, "one reconnect counted, the refused hmd counted");
        StreamHeadset(input, new byte[0], new byte[0], 90, 200, 9);
        WaitFor(() => input.TryTakePose(out pose) && pose.Seq >= 200, "poses after the reconnect");
        Check(pose != null && pose.Model == "hmd", "from the resumed model");
        input.Dispose();
    }

    /// <summary>hmd at <paramref name="hz"/> with an rgbd every third sample; {seq: t_us} of the hmd sent.</summary>
    static Dictionary<long, long> StreamHeadset(EgoPoseConnection input, byte[] rgb, byte[] depth, int hz, int first, int count)
    {
        var sent = new Dictionary<long, long>();
        var start = DateTime.UtcNow;
        for (int i = first; i < first + count; i++)
        {
            long tUs = 1000000 + i * 1000000L / hz;
            double sway = 0.05 * Math.Sin(i * 0.1);
            var hmd = new Hmd
            {
                Seq = i, TUs = tUs,
                Head = new[] { (float)sway, 1.6f, 0f, 0f, 0f, 0f, 1f },
                Left = new[] { -0.25f, 1.0f, -0.25f, 0f, 0f, 0f, 1f },
                Right = new[] { 0.25f, 1.0f, -0.25f, 0f, 0f, 0f, 1f },
            };
            Check(input.Send(hmd), "hmd " + i + " queued");
            sent[i] = tUs;
            if (i % 3 == 0 && rgb.Length > 0)
            {
                input.Send(new Rgbd
                {
                    Seq = i / 3, TUs = tUs, Width = 160, Height = 128, Intrinsics = new[] { 80f, 80f, 80f, 64f },
                    Rgb = rgb, Depth = depth,
                });
            }
            var due = start + TimeSpan.FromTicks((i - first + 1) * TimeSpan.TicksPerSecond / hz);
            var wait = due - DateTime.UtcNow;
            if (wait > TimeSpan.Zero) Thread.Sleep(wait);
        }
        return sent;
    }

    /// <summary>Bytes that are no msgpack value, on a raw socket: an error, not fatal, and the socket stays up.</summary>
    static void MalformedMessage(string url, string session)
    {
        using (var socket = new ClientWebSocket())
        {
            var token = new CancellationTokenSource(TimeSpan.FromSeconds(10)).Token;
            socket.ConnectAsync(new Uri(url + "?session=" + session), token).Wait();
            Send(socket, new Hello { Role = "render", Session = session }.Encode(), token);
            Send(socket, new byte[] { 0xc1 }, token);
            Error error = null;
            while (error == null)
                error = Receive(socket, token) as Error;
            Check(error.Code == "malformed" && !error.Fatal, "a malformed message gets a non-fatal malformed error");
            Send(socket, new Ping { Nonce = 5 }.Encode(), token);
            Pong pong = null;
            while (pong == null)
                pong = Receive(socket, token) as Pong;
            Check(pong.Nonce == 5 && socket.State == WebSocketState.Open, "the connection stays up after it");
        }
    }

    static void Send(ClientWebSocket socket, byte[] data, CancellationToken token)
    {
        socket.SendAsync(new ArraySegment<byte>(data), WebSocketMessageType.Binary, true, token).Wait();
    }

    static Message Receive(ClientWebSocket socket, CancellationToken token)
    {
        var buffer = new byte[1 << 20];
        int length = 0;
        WebSocketReceiveResult result;
        do
        {
            result = socket.ReceiveAsync(new ArraySegment<byte>(buffer, length, buffer.Length - length), token).Result;
            length += result.Count;
        } while (!result.EndOfMessage);
        return Protocol.DecodeFromServer(buffer, 0, length);
    }

    static T WaitForMessage<T>(EgoPoseConnection connection, Func<T, bool> wanted, string what) where T : Message
    {
        var deadline = DateTime.UtcNow + TimeSpan.FromSeconds(15);
        while (DateTime.UtcNow < deadline)
        {
            Message message;
            while (connection.TryDequeue(out message))
            {
                var typed = message as T;
                if (typed != null && wanted(typed))
                {
                    checks++;
                    return typed;
                }
            }
            Thread.Sleep(5);
        }
        throw new Exception("timed out waiting for " + what + " (state " + connection.State + ", last error "
                            + connection.LastError + ")");
    }

    static void WaitFor(Func<bool> condition, string what)
    {
        var deadline = DateTime.UtcNow + TimeSpan.FromSeconds(30);
        while (!condition())
        {
            if (DateTime.UtcNow > deadline) throw new Exception("timed out waiting until " + what);
            Thread.Sleep(5);
        }
        checks++;
    }
}
