// Coordinate frames (PROTOCOL.md §3): the protocol's world is right-handed, +Y up, -Z forward (OpenXR's stage
// space); Unity's is left-handed, +Y up, +Z forward. The map between them mirrors Z and is its own inverse:
//   position (x, y, z) <-> (x, y, -z);   quaternion (x, y, z, w) <-> (-x, -y, z, w)
// Quaternions are [x, y, z, w], Hamilton, rotating a device's local axes into the world. Poses are
// [px, py, pz, qx, qy, qz, qw].
//
// Pure C#: no UnityEngine (Unity's Vector3/Quaternion are copied in and out as floats by the Unity layer).
using System;

namespace EgoPose.Protocol
{
    /// <summary>One XR device as Unity's XR input reports it (Unity's frame) with its tracking state bits.</summary>
    public struct UnityDevicePose
    {
        public float[] Position; // Unity world (tracking space) metres: x, y, z
        public float[] Rotation; // Unity quaternion x, y, z, w
        public int TrackingState; // UnityEngine.XR.InputTrackingState bits: Position = 1, Rotation = 2

        public UnityDevicePose(float[] position, float[] rotation, int trackingState)
        {
            Position = position;
            Rotation = rotation;
            TrackingState = trackingState;
        }
    }

    public static class Frames
    {
        public const int TrackedPosition = 1; // InputTrackingState.Position
        public const int TrackedRotation = 2; // InputTrackingState.Rotation
        static readonly double Half = Math.Sqrt(0.5);

        /// <summary>What an untracked device sends: its numbers are ignored by the server (§5 hmd).</summary>
        public static readonly float[] UntrackedPose = { 0f, 0f, 0f, 0f, 0f, 0f, 1f };

        /// <summary>Protocol position from Unity's, and back (the map is its own inverse).</summary>
        public static float[] MirrorPosition(float[] p) { return new[] { p[0], p[1], -p[2] }; }

        /// <summary>Protocol quaternion from Unity's, and back.</summary>
        public static float[] MirrorRotation(float[] q) { return new[] { -q[0], -q[1], q[2], q[3] }; }

        /// <summary>Hamilton product a ⊗ b of [x, y, z, w] quaternions (b applied first, in a's frame).</summary>
        public static float[] Multiply(float[] a, float[] b)
        {
            return Multiply(a, 0, b, 0);
        }

        public static float[] Multiply(float[] a, int ai, float[] b, int bi)
        {
            return Multiply(a[ai], a[ai + 1], a[ai + 2], a[ai + 3], b[bi], b[bi + 1], b[bi + 2], b[bi + 3]);
        }

        // In double, rounded once at the end: the same float32 the server's own (Python) conversion sends.
        static float[] Multiply(double ax, double ay, double az, double aw, double bx, double by, double bz, double bw)
        {
            return new[]
            {
                (float)(aw * bx + ax * bw + ay * bz - az * by),
                (float)(aw * by - ax * bz + ay * bw + az * bx),
                (float)(aw * bz + ax * by - ay * bx + az * bw),
                (float)(aw * bw - ax * bx - ay * by - az * bz),
            };
        }

        public static float[] Inverse(float[] q) { return new[] { -q[0], -q[1], -q[2], q[3] }; }

        /// <summary>Quaternion [x, y, z, w] of an axis-angle vector (radians), as SMPL's rotations are sent.</summary>
        public static float[] FromAxisAngle(float[] a, int offset)
        {
            double x = a[offset], y = a[offset + 1], z = a[offset + 2];
            double angle = Math.Sqrt(x * x + y * y + z * z);
            if (angle < 1e-12) return new[] { 0f, 0f, 0f, 1f };
            double s = Math.Sin(angle / 2) / angle;
            return new[] { (float)(x * s), (float)(y * s), (float)(z * s), (float)Math.Cos(angle / 2) };
        }

        /// <summary>The protocol's controller pose from an OpenXR grip pose (both in the protocol's frame, §3.3):
        /// the grip's orientation turned a quarter turn about its own Z, +90° for the left hand, -90° for the right.</summary>
        public static float[] ControllerFromGrip(float[] gripPose, bool leftHand)
        {
            var q = Multiply(gripPose[3], gripPose[4], gripPose[5], gripPose[6], 0, 0, leftHand ? Half : -Half, Half);
            return new[] { gripPose[0], gripPose[1], gripPose[2], q[0], q[1], q[2], q[3] };
        }

        /// <summary>The protocol's <c>valid</c> from Unity's tracking state: position and rotation both known.</summary>
        public static bool IsValid(int trackingState)
        {
            const int both = TrackedPosition | TrackedRotation;
            return (trackingState & both) == both;
        }

        /// <summary>A device pose in the protocol's frame from Unity's position and rotation.</summary>
        public static float[] PoseFromUnity(float[] position, float[] rotation)
        {
            var p = MirrorPosition(position);
            var q = MirrorRotation(rotation);
            return new[] { p[0], p[1], p[2], q[0], q[1], q[2], q[3] };
        }

        /// <summary>
        /// An <c>hmd</c> message from Unity's XR input: the head (the centre-eye device: OpenXR's VIEW space) and
        /// the two controllers' device poses, which Unity's OpenXR plugin reports as the grip pose. Untracked
        /// devices (orientation-only counts as untracked, §3.3) are sent as <see cref="UntrackedPose"/>.
        /// </summary>
        public static Hmd HmdFromUnity(long seq, long tUs, UnityDevicePose head, UnityDevicePose left,
            UnityDevicePose right)
        {
            var valid = new[] { IsValid(head.TrackingState), IsValid(left.TrackingState), IsValid(right.TrackingState) };
            return new Hmd
            {
                Seq = seq,
                TUs = tUs,
                Head = valid[0] ? PoseFromUnity(head.Position, head.Rotation) : (float[])UntrackedPose.Clone(),
                Left = valid[1]
                    ? ControllerFromGrip(PoseFromUnity(left.Position, left.Rotation), true)
                    : (float[])UntrackedPose.Clone(),
                Right = valid[2]
                    ? ControllerFromGrip(PoseFromUnity(right.Position, right.Rotation), false)
                    : (float[])UntrackedPose.Clone(),
                Valid = valid,
            };
        }
    }
}
