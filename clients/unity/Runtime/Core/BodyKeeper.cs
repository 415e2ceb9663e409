// A headset app's memory of its wearer's body between sessions (PROTOCOL.md §4.2): the server measures the body
// in a session's first seconds and resizes the served skeleton as it learns it, so still legs move while it does;
// a client that gives the body it kept from an earlier session gets the wearer's size from the first sample.
//
//   var keeper = new BodyKeeper(BodyKeeper.Parse(storedText));          // null text or none kept: estimate
//   connection options: Body = keeper.Kept                              // given after every welcome
//   each frame:   Message ask = keeper.Poll(nowS); if (ask != null) connection.Send(ask);
//                 foreach message: if (keeper.Take(message)) store(BodyKeeper.Format(keeper.Kept));   // or delete
//
// While the session estimates the body (no body given to it) it asks the server (get_body) every
// AskEverySeconds and keeps the newest body the server says is measured: the later, the more the camera has seen.
// Once the session serves a given body (ours, after the next welcome) there is nothing new to learn, and it stops
// asking. A kept body the server refuses (out_of_range) is forgotten. Pure C#, no UnityEngine, not thread-safe:
// call it from one thread (Unity's main thread).
using System;
using System.Globalization;
using System.Linq;

namespace EgoPose.Protocol
{
    public sealed class BodyKeeper
    {
        readonly double askEverySeconds;
        double nextAskS = double.NegativeInfinity;
        bool sessionGiven; // the newest body message said the session serves a given body

        /// <param name="kept">the body kept from an earlier session (21 bone lengths, m), or null</param>
        /// <param name="askEverySeconds">while the session estimates the body, how often to ask for its estimate</param>
        public BodyKeeper(float[] kept, double askEverySeconds = 15.0)
        {
            if (kept != null && !Valid(kept)) throw new ArgumentException("a kept body must hold 21 positive finite lengths");
            if (!(askEverySeconds > 0)) throw new ArgumentException("askEverySeconds must be > 0");
            Kept = kept == null ? null : (float[])kept.Clone();
            this.askEverySeconds = askEverySeconds;
        }

        /// <summary>The wearer's kept body (21 bone lengths, m), or null while none is.</summary>
        public float[] Kept { get; private set; }

        /// <summary>A <see cref="GetBody"/> to send now (the session estimates, and the last ask is old enough), or null.</summary>
        public Message Poll(double nowS)
        {
            if (sessionGiven || nowS < nextAskS) return null;
            nextAskS = nowS + askEverySeconds;
            return new GetBody();
        }

        /// <summary>
        /// Read a server message; true when <see cref="Kept"/> changed (store it, or delete what was stored when it
        /// is null): a new measured body the server estimated, or a kept body the server refused.
        /// </summary>
        public bool Take(Message message)
        {
            var body = message as Body;
            if (body != null) sessionGiven = body.Given;
            if (body != null && body.Measured && !body.Given && Valid(body.BoneLengthsM)
                && (Kept == null || !Kept.SequenceEqual(body.BoneLengthsM)))
            {
                Kept = (float[])body.BoneLengthsM.Clone();
                return true;
            }
            var error = message as Error;
            if (error != null && Kept != null && error.RefusesBody)
            {
                Kept = null;
                return true;
            }
            return false;
        }

        /// <summary>Forget the kept body (the wearer changed); send the returned message so the session estimates again.</summary>
        public SetBody Forget()
        {
            Kept = null;
            sessionGiven = false;
            nextAskS = double.NegativeInfinity;
            return new SetBody { Clear = true };
        }

        /// <summary>A kept body as text for a preferences store: 21 comma-separated lengths in metres.</summary>
        public static string Format(float[] boneLengthsM)
        {
            if (!Valid(boneLengthsM)) throw new ArgumentException("a body holds 21 positive finite lengths");
            var items = new string[boneLengthsM.Length];
            for (int i = 0; i < items.Length; i++) items[i] = boneLengthsM[i].ToString("R", CultureInfo.InvariantCulture);
            return string.Join(",", items);
        }

        /// <summary>The body <see cref="Format"/> wrote, or null for no text or text that is not one (a damaged store).</summary>
        public static float[] Parse(string text)
        {
            if (string.IsNullOrEmpty(text)) return null;
            string[] items = text.Split(',');
            if (items.Length != Body.BoneCount) return null;
            var lengths = new float[items.Length];
            for (int i = 0; i < items.Length; i++)
            {
                if (!float.TryParse(items[i], NumberStyles.Float, CultureInfo.InvariantCulture, out lengths[i])) return null;
            }
            return Valid(lengths) ? lengths : null;
        }

        static bool Valid(float[] lengths)
        {
            if (lengths == null || lengths.Length != Body.BoneCount) return false;
            foreach (float length in lengths)
            {
                if (float.IsNaN(length) || float.IsInfinity(length) || length <= 0) return false;
            }
            return true;
        }
    }
}
