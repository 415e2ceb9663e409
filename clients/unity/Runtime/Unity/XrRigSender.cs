// Sends the headset and both controllers to the server as `hmd` messages, one per rendered frame (the display
// rate: 72-120 Hz), from Unity's XR input (UnityEngine.XR.InputDevices; with the OpenXR plugin the head is the
// centre eye, OpenXR's VIEW space, and a controller's device pose is its grip pose). Core/Frames.cs turns them
// into the protocol's frame (PROTOCOL.md §3.1, §3.3).
//
// Needs UnityEngine: not compiled by the project's tests (Frames.HmdFromUnity, which does the work, is).
using EgoPose.Protocol;
using UnityEngine;
using UnityEngine.XR;

namespace EgoPose
{
    [AddComponentMenu("EgoPose/XR Rig Sender")]
    [RequireComponent(typeof(EgoPoseClient))]
    public sealed class XrRigSender : MonoBehaviour
    {
        [Tooltip("Send in Application.onBeforeRender (the freshest poses of the frame) instead of Update")]
        public bool sendBeforeRender = true;

        EgoPoseClient client;
        long seq;

        /// <summary>Samples the server will not get because the connection was down.</summary>
        public long Dropped { get; private set; }

        void Awake()
        {
            client = GetComponent<EgoPoseClient>();
        }

        void OnEnable()
        {
            // The XR origin should use a floor-level tracking space: the protocol's floor is y = 0 (§3).
            var subsystems = new System.Collections.Generic.List<XRInputSubsystem>();
            SubsystemManager.GetInstances(subsystems);
            foreach (var subsystem in subsystems) subsystem.TrySetTrackingOriginMode(TrackingOriginModeFlags.Floor);
            if (sendBeforeRender) Application.onBeforeRender += SendSample;
        }

        void OnDisable()
        {
            Application.onBeforeRender -= SendSample;
        }

        void Update()
        {
            if (!sendBeforeRender) SendSample();
        }

        void SendSample()
        {
            var head = Read(XRNode.CenterEye, CommonUsages.centerEyePosition, CommonUsages.centerEyeRotation);
            var left = Read(XRNode.LeftHand, CommonUsages.devicePosition, CommonUsages.deviceRotation);
            var right = Read(XRNode.RightHand, CommonUsages.devicePosition, CommonUsages.deviceRotation);
            var hmd = Frames.HmdFromUnity(seq++, EgoPoseConnection.NowUs(), head, left, right);
            if (!client.Send(hmd)) Dropped++;
        }

        static UnityDevicePose Read(XRNode node, InputFeatureUsage<Vector3> positionUsage,
            InputFeatureUsage<Quaternion> rotationUsage)
        {
            var device = InputDevices.GetDeviceAtXRNode(node);
            if (!device.isValid && node == XRNode.CenterEye) device = InputDevices.GetDeviceAtXRNode(XRNode.Head);
            Vector3 p;
            Quaternion q;
            InputTrackingState state;
            if (!device.isValid
                || !device.TryGetFeatureValue(CommonUsages.trackingState, out state)
                || !(device.TryGetFeatureValue(positionUsage, out p) || device.TryGetFeatureValue(CommonUsages.devicePosition, out p))
                || !(device.TryGetFeatureValue(rotationUsage, out q) || device.TryGetFeatureValue(CommonUsages.deviceRotation, out q)))
                return new UnityDevicePose(new float[3], new[] { 0f, 0f, 0f, 1f }, 0); // untracked
            return new UnityDevicePose(new[] { p.x, p.y, p.z }, new[] { q.x, q.y, q.z, q.w }, (int)state);
        }
    }
}
