// Drives any Humanoid avatar (Mixamo, VRM, Ready Player Me, ...) with the served SMPL rotations: each mapped bone
// gets its world rotation from Core/SmplRetarget.cs, which accounts for how that rig rests its bones, and the
// hips go where the pose's `transl` says. The avatar must stand in its T-pose when the driver starts (most
// humanoids import so; otherwise use "Enforce T-Pose" in the avatar's configuration). A foot the server holds
// planted (PROTOCOL.md §planted-feet) stays where the avatar's foot landed (Core/FootPins.cs: two-bone IK on the
// thigh and shin), so an avatar of other proportions does not slide its feet as the hips move over them.
//
// Needs UnityEngine: not compiled by the project's tests (the retargeting math it calls is, against Python).
using EgoPose.Protocol;
using UnityEngine;

namespace EgoPose
{
    [AddComponentMenu("EgoPose/SMPL Humanoid Driver")]
    public sealed class SmplHumanoidDriver : MonoBehaviour
    {
        [Tooltip("Where the poses come from")]
        public EgoPoseClient client;

        [Tooltip("The humanoid avatar to drive (its Animator's avatar must be Humanoid)")]
        public Animator avatar;

        [Tooltip("The XR tracking space (the XR origin's transform); empty: world = tracking space")]
        public Transform trackingSpace;

        [Tooltip("Scale the hips' height by the avatar's leg length over the wearer's, so a smaller avatar stands on the floor")]
        public bool matchAvatarHeight = true;

        [Tooltip("Keep each foot the server holds planted where the avatar's foot landed (two-bone IK on the leg)")]
        public bool pinPlantedFeet = true;

        static readonly int[][] Legs = { new[] { 1, 4, 7 }, new[] { 2, 5, 8 } }; // hip, knee, ankle: left, right
        readonly FootPins pins = new FootPins();
        Transform[] bones;
        float[] tposeWorld; // 22 × xyzw, relative to the avatar's root rotation
        float avatarLegLength;

        void Start()
        {
            bones = new Transform[SmplRetarget.JointCount];
            tposeWorld = new float[SmplRetarget.JointCount * 4];
            var rootInverse = Quaternion.Inverse(avatar.transform.rotation);
            for (int j = 0; j < SmplRetarget.JointCount; j++)
            {
                var bone = (HumanBodyBones)System.Enum.Parse(typeof(HumanBodyBones), SmplRetarget.HumanBones[j]);
                bones[j] = avatar.GetBoneTransform(bone); // null for optional bones the rig lacks
                var rest = bones[j] == null ? Quaternion.identity : rootInverse * bones[j].rotation;
                tposeWorld[4 * j] = rest.x;
                tposeWorld[4 * j + 1] = rest.y;
                tposeWorld[4 * j + 2] = rest.z;
                tposeWorld[4 * j + 3] = rest.w;
            }
            avatarLegLength = Distance(HumanBodyBones.LeftUpperLeg, HumanBodyBones.LeftLowerLeg)
                              + Distance(HumanBodyBones.LeftLowerLeg, HumanBodyBones.LeftFoot);
        }

        float Distance(HumanBodyBones a, HumanBodyBones b)
        {
            return Vector3.Distance(avatar.GetBoneTransform(a).position, avatar.GetBoneTransform(b).position);
        }

        void LateUpdate()
        {
            var pose = client == null ? null : client.LatestPose;
            if (pose == null) return;
            var world = SmplRetarget.AvatarWorldRotations(SmplRetarget.WorldRotations(pose.GlobalOrient, pose.BodyPose), tposeWorld);
            var space = trackingSpace == null ? Quaternion.identity : trackingSpace.rotation;
            for (int j = 0; j < SmplRetarget.JointCount; j++) // parents before children: each bone's world rotation is final
            {
                if (bones[j] == null) continue;
                bones[j].rotation = space * new Quaternion(world[4 * j], world[4 * j + 1], world[4 * j + 2], world[4 * j + 3]);
            }
            float servedLeg = SmplRetarget.LegLength(pose.Joints);
            float scale = matchAvatarHeight && servedLeg > 0.1f ? avatarLegLength / servedLeg : 1f;
            var hips = SmplRetarget.HipsPosition(pose.Transl, scale);
            var position = new Vector3(hips[0], hips[1], hips[2]);
            bones[0].position = trackingSpace == null ? position : trackingSpace.TransformPoint(position);
            // The body's front, for a straight knee to bend towards: up × (left hip − right hip), in Unity's frame.
            Vector3 left = bones[1].position, right = bones[2].position;
            var forward = new[] { left.z - right.z, 0f, right.x - left.x };
            for (int side = 0; side < 2; side++) PinFoot(pose, side, forward);
        }

        void PinFoot(Pose pose, int side, float[] forward)
        {
            Transform upper = bones[Legs[side][0]], lower = bones[Legs[side][1]], foot = bones[Legs[side][2]];
            bool planted = pinPlantedFeet && pose.Planted != null && pose.Planted[side];
            float[] hip = Xyz(upper.position), ankle = Xyz(foot.position);
            var target = pins.Target(side, planted, pose.TUs, hip, ankle, avatarLegLength);
            if (target == null) return;
            var footRotation = foot.rotation; // the foot keeps its world rotation while the leg bends to reach
            float[] kneeTurn, thighTurn;
            FootPins.Reach(hip, Xyz(lower.position), ankle, target, forward, out kneeTurn, out thighTurn);
            lower.rotation = Rotation(kneeTurn) * lower.rotation;
            upper.rotation = Rotation(thighTurn) * upper.rotation;
            foot.rotation = footRotation;
        }

        static float[] Xyz(Vector3 v) { return new[] { v.x, v.y, v.z }; }

        static Quaternion Rotation(float[] q) { return new Quaternion(q[0], q[1], q[2], q[3]); }
    }
}
