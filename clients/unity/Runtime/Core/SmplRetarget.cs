// From a pose's SMPL rotations to the world rotations of any humanoid avatar's bones, on plain arrays.
//
// SMPL's rest pose is a T-pose facing the protocol's +Z (PROTOCOL.md §3); a joint's world rotation is the
// product of global_orient and the local rotations down its chain, and rotates the rest pose's bone into the
// served one. Mirrored into Unity's frame, that rest pose faces Unity's -Z. A Unity humanoid's T-pose faces +Z,
// and each of its bones has a rest rotation of its own (rigs differ: Mixamo, VRM, ...). So for avatar bone j
// with world rotation T_j in its T-pose (avatar root at identity):
//
//   A_j = U_j · Y180 · T_j        U_j: SMPL joint j's world rotation, mirrored into Unity's frame
//
// which is T_j at rest turned to face -Z, then moved as SMPL moved. Missing bones (no UpperChest, no toes) are
// skipped: every present bone is given its world rotation, so its children stay right.
//
// Quaternions are [x, y, z, w]; arrays of 22 joints hold 88 floats (joint-major).
// Pure C#: no UnityEngine (SmplHumanoidDriver.cs applies the result to Transforms).
using System;

namespace EgoPose.Protocol
{
    public static class SmplRetarget
    {
        public const int JointCount = 22;

        /// <summary>SMPL's parent of each joint (-1: the root), PROTOCOL.md §3.</summary>
        public static readonly int[] Parents = { -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19 };

        /// <summary>The name of Unity's HumanBodyBones member for each SMPL joint (its enum parses these).</summary>
        public static readonly string[] HumanBones =
        {
            "Hips", "LeftUpperLeg", "RightUpperLeg", "Spine", "LeftLowerLeg", "RightLowerLeg", "Chest",
            "LeftFoot", "RightFoot", "UpperChest", "LeftToes", "RightToes", "Neck", "LeftShoulder",
            "RightShoulder", "Head", "LeftUpperArm", "RightUpperArm", "LeftLowerArm", "RightLowerArm",
            "LeftHand", "RightHand",
        };

        static readonly float[] Yaw180 = { 0f, 1f, 0f, 0f };

        /// <summary>World rotations [22 × xyzw] in the protocol's frame from global_orient [3] and body_pose [63].</summary>
        public static float[] WorldRotations(float[] globalOrient, float[] bodyPose)
        {
            if (globalOrient.Length != 3 || bodyPose.Length != 63)
                throw new ArgumentException("expected global_orient[3] and body_pose[63]");
            var world = new float[JointCount * 4];
            Put(world, 0, Frames.FromAxisAngle(globalOrient, 0));
            for (int j = 1; j < JointCount; j++)
            {
                var local = Frames.FromAxisAngle(bodyPose, 3 * (j - 1));
                Put(world, j, Frames.Multiply(world, 4 * Parents[j], local, 0));
            }
            return world;
        }

        /// <summary>
        /// Each avatar bone's world rotation in Unity's frame [22 × xyzw]: the pose's world rotations
        /// (<see cref="WorldRotations"/>) applied to the avatar's T-pose world rotations <paramref name="tposeWorld"/>
        /// [22 × xyzw, avatar root at identity facing +Z].
        /// </summary>
        public static float[] AvatarWorldRotations(float[] smplWorld, float[] tposeWorld)
        {
            var result = new float[JointCount * 4];
            for (int j = 0; j < JointCount; j++)
            {
                var unity = Frames.MirrorRotation(Slice(smplWorld, j));
                var turned = Frames.Multiply(unity, Yaw180);
                Put(result, j, Normalised(Frames.Multiply(turned, Slice(tposeWorld, j))));
            }
            return result;
        }

        /// <summary>The pelvis position in Unity's frame, its height scaled by avatar leg / served leg
        /// (<paramref name="heightScale"/>, 1 to keep the wearer's) so that a shorter avatar's feet stay on the floor.</summary>
        public static float[] HipsPosition(float[] transl, float heightScale)
        {
            var p = Frames.MirrorPosition(transl);
            p[1] *= heightScale;
            return p;
        }

        /// <summary>Hip-to-ankle length (m) of a pose's left leg: joints [66] hip 1, knee 4, ankle 7.</summary>
        public static float LegLength(float[] joints)
        {
            return Distance(joints, 1, 4) + Distance(joints, 4, 7);
        }

        static float Distance(float[] joints, int a, int b)
        {
            float dx = joints[3 * a] - joints[3 * b], dy = joints[3 * a + 1] - joints[3 * b + 1];
            float dz = joints[3 * a + 2] - joints[3 * b + 2];
            return (float)Math.Sqrt(dx * dx + dy * dy + dz * dz);
        }

        static float[] Slice(float[] quats, int j)
        {
            return new[] { quats[4 * j], quats[4 * j + 1], quats[4 * j + 2], quats[4 * j + 3] };
        }

        static void Put(float[] quats, int j, float[] q)
        {
            Array.Copy(q, 0, quats, 4 * j, 4);
        }

        static float[] Normalised(float[] q)
        {
            float n = (float)Math.Sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
            return new[] { q[0] / n, q[1] / n, q[2] / n, q[3] / n };
        }
    }
}
