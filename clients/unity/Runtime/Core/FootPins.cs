// Planted feet kept where they landed on an avatar of other proportions (PROTOCOL.md §planted-feet).
//
// SmplHumanoidDriver copies the served rotations onto the avatar and scales the hips' height to its legs. An
// avatar whose legs are not the wearer's then moves its feet whenever the hips move over them, even while the
// server holds them planted. FootPins remembers where each planted foot landed, and Reach gives the two-bone IK
// turns (knee, then thigh) that put the foot back there as far as the leg reaches.
//
// Positions [x, y, z] and quaternions [x, y, z, w] in any one frame (the driver's: Unity's world).
// Pure C#: no UnityEngine.
using System;

namespace EgoPose.Protocol
{
    public sealed class FootPins
    {
        /// <summary>A pin farther than this many leg lengths from its hip is dropped (a recentred space).</summary>
        public const float Slack = 1.2f;

        /// <summary>Pins are dropped after a pause this long between poses (µs): the next pose lands anew.</summary>
        public const long GapUs = 500000;

        /// <summary>The knee's way off its hip-to-ankle line gets this much (m) of the body's front added.</summary>
        public const double FrontPullM = 0.1;

        readonly float[][] pins = new float[2][];
        long lastTUs = -1;

        /// <summary>
        /// Where foot <paramref name="side"/> (0 left, 1 right) should be for the pose at <paramref name="tUs"/>:
        /// null while it is not planted, or in the pose where it lands (it stays where the pose put it,
        /// <paramref name="foot"/>, which becomes its pin); afterwards, that pin. Call once per side and pose.
        /// </summary>
        public float[] Target(int side, bool planted, long tUs, float[] hip, float[] foot, float legLength)
        {
            if (side == 0)
            {
                if (lastTUs >= 0 && (tUs < lastTUs || tUs - lastTUs > GapUs)) pins[0] = pins[1] = null;
                lastTUs = tUs;
            }
            if (!planted)
            {
                pins[side] = null;
                return null;
            }
            if (pins[side] == null || Distance(pins[side], hip) > Slack * legLength)
            {
                pins[side] = (float[])foot.Clone();
                return null;
            }
            return pins[side];
        }

        /// <summary>
        /// Two-bone IK: the world turns that bring the foot from <paramref name="ankle"/> to <paramref name="target"/>
        /// as far as the thigh and shin reach. <paramref name="kneeTurn"/> turns the shin about the knee so that hip
        /// to foot spans the hip's distance to the target;
        /// <paramref name="thighTurn"/>, applied after it, swings the thigh (and the shin with it) about the hip to
        /// point the chain at the target. Both as a new world rotation = turn · old world rotation. The knee goes
        /// the way it sits off the hip-to-ankle line, pulled towards <paramref name="forward"/> (the body's front).
        /// </summary>
        public static void Reach(float[] hip, float[] knee, float[] ankle, float[] target, float[] forward,
                                 out float[] kneeTurn, out float[] thighTurn)
        {
            double[] toHip = Sub(hip, knee), toAnkle = Sub(ankle, knee);
            double thigh = Norm(toHip), shin = Norm(toAnkle);
            double span = Math.Max(Math.Abs(thigh - shin) + 1e-4, Math.Min(thigh + shin - 1e-4, Norm(Sub(target, hip))));
            // The way the knee goes: where it is off the hip-to-ankle line, pulled to the body's front (a leg about
            // straight, or one whose rest knee sits off the line sideways, bends forward, not out).
            double[] line = Normalised(Sub(ankle, hip));
            double[] front = Normalised(new double[] { forward[0], forward[1], forward[2] });
            double[] way = Add(Across(Sub(knee, hip), line), Scale(Across(front, line), FrontPullM));
            double[] axis = Cross(way, toHip);
            double wanted = Math.Acos(Clamp((thigh * thigh + shin * shin - span * span) / (2 * thigh * shin)));
            // the shin's new way: the thigh's (knee to hip) turned by the knee angle wanted, in the bend plane
            double[] shinWay = Rotate(AxisAngle(Normalised(axis), wanted), Normalised(toHip));
            var knee64 = FromTo(Normalised(toAnkle), shinWay);
            double[] reached = Add(Sub(knee, hip), Rotate(knee64, toAnkle)); // hip to the turned ankle
            var thigh64 = FromTo(Normalised(reached), Normalised(Sub(target, hip)));
            kneeTurn = ToFloat(knee64);
            thighTurn = ToFloat(thigh64);
        }

        /// <summary>The vector <paramref name="v"/> [3] turned by the quaternion <paramref name="q"/> [xyzw].</summary>
        public static float[] Rotate(float[] q, float[] v)
        {
            var r = Rotate(new double[] { q[0], q[1], q[2], q[3] }, new double[] { v[0], v[1], v[2] });
            return new[] { (float)r[0], (float)r[1], (float)r[2] };
        }

        static double[] Rotate(double[] q, double[] v)
        {
            double[] u = { q[0], q[1], q[2] };
            double[] t = Scale(Cross(u, v), 2);
            return Add(Add(v, Scale(t, q[3])), Cross(u, t));
        }

        static double[] AxisAngle(double[] unitAxis, double angle)
        {
            double s = Math.Sin(angle / 2);
            return new[] { unitAxis[0] * s, unitAxis[1] * s, unitAxis[2] * s, Math.Cos(angle / 2) };
        }

        static double[] FromTo(double[] a, double[] b)
        {
            double w = 1 + Dot(a, b);
            if (w < 1e-9) return AxisAngle(Normalised(Perpendicular(a)), Math.PI); // opposite: half a turn
            double[] c = Cross(a, b);
            double n = Math.Sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + w * w);
            return new[] { c[0] / n, c[1] / n, c[2] / n, w / n };
        }

        static double[] Across(double[] v, double[] unitLine) { return Sub(v, Scale(unitLine, Dot(v, unitLine))); }

        static double[] Perpendicular(double[] v)
        {
            return Math.Abs(v[0]) < 0.9 ? Cross(v, new double[] { 1, 0, 0 }) : Cross(v, new double[] { 0, 1, 0 });
        }

        static double Clamp(double c) { return Math.Max(-1.0, Math.Min(1.0, c)); }
        static double[] Sub(float[] a, float[] b) { return new double[] { a[0] - b[0], a[1] - b[1], a[2] - b[2] }; }
        static double[] Sub(double[] a, double[] b) { return new[] { a[0] - b[0], a[1] - b[1], a[2] - b[2] }; }
        static double[] Add(double[] a, double[] b) { return new[] { a[0] + b[0], a[1] + b[1], a[2] + b[2] }; }
        static double[] Scale(double[] a, double s) { return new[] { a[0] * s, a[1] * s, a[2] * s }; }
        static double Dot(double[] a, double[] b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
        static double Norm(double[] a) { return Math.Sqrt(Dot(a, a)); }
        static double[] Normalised(double[] a) { return Scale(a, 1 / Norm(a)); }
        static float Distance(float[] a, float[] b) { return (float)Norm(Sub(a, b)); }
        static float[] ToFloat(double[] q) { return new[] { (float)q[0], (float)q[1], (float)q[2], (float)q[3] }; }

        static double[] Cross(double[] a, double[] b)
        {
            return new[] { a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0] };
        }
    }
}
