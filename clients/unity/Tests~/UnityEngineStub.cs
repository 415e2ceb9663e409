// The few UnityEngine types the package's Unity layer (Runtime/Unity, Samples~) uses, declared with Unity's
// signatures and no behaviour, so that tests/clients/test_unity_core.py can compile that layer with Mono and catch
// a typo or a wrong type before a Unity user does. It proves nothing about what those calls do in Unity.
// Not part of the package (Unity ignores folders ending in ~).
using System;
using System.Collections.Generic;

namespace UnityEngine.Events
{
    public delegate void UnityAction();
}

namespace UnityEngine
{
    public class Object { }

    public class Component : Object
    {
        public Transform transform { get { return null; } }
        public T GetComponent<T>() { return default(T); }
    }

    public class Behaviour : Component { public bool enabled { get; set; } }

    public class MonoBehaviour : Behaviour { }

    public class Transform : Component
    {
        public Vector3 position { get; set; }
        public Quaternion rotation { get; set; }
        public Vector3 TransformPoint(Vector3 position) { return position; }
    }

    public class Animator : Behaviour
    {
        public Transform GetBoneTransform(HumanBodyBones humanBoneId) { return null; }
    }

    public enum HumanBodyBones
    {
        Hips, LeftUpperLeg, RightUpperLeg, LeftLowerLeg, RightLowerLeg, LeftFoot, RightFoot, Spine, Chest, Neck, Head,
        LeftShoulder, RightShoulder, LeftUpperArm, RightUpperArm, LeftLowerArm, RightLowerArm, LeftHand, RightHand,
        LeftToes, RightToes, UpperChest = 54,
    }

    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public static float Distance(Vector3 a, Vector3 b) { return 0f; }
    }

    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
        public static Quaternion identity { get { return new Quaternion(0, 0, 0, 1); } }
        public static Quaternion Inverse(Quaternion rotation) { return rotation; }
        public static Quaternion operator *(Quaternion lhs, Quaternion rhs) { return lhs; }
    }

    public struct Rect
    {
        public Rect(float x, float y, float width, float height) { }
    }

    public static class Debug
    {
        public static void LogWarning(object message) { }
    }

    public static class Application
    {
        public static string unityVersion { get { return ""; } }
        public static event Events.UnityAction onBeforeRender { add { } remove { } }
    }

    public static class PlayerPrefs
    {
        public static string GetString(string key, string defaultValue) { return defaultValue; }
        public static void SetString(string key, string value) { }
        public static void DeleteKey(string key) { }
        public static void Save() { }
    }

    public static class Time
    {
        public static float unscaledTime { get { return 0f; } }
    }

    public static class SystemInfo
    {
        public static string deviceModel { get { return ""; } }
    }

    public static class GUILayout
    {
        public static void BeginArea(Rect screenRect) { }
        public static void EndArea() { }
        public static void Label(string text, params GUILayoutOption[] options) { }
        public static bool Button(string text, params GUILayoutOption[] options) { return false; }
    }

    public sealed class GUILayoutOption { }

    public interface ISubsystem { }

    public static class SubsystemManager
    {
        public static void GetInstances<T>(List<T> subsystems) where T : ISubsystem { }
    }

    [AttributeUsage(AttributeTargets.Class)]
    public sealed class AddComponentMenu : Attribute { public AddComponentMenu(string menuName) { } }

    [AttributeUsage(AttributeTargets.Class, AllowMultiple = true)]
    public sealed class RequireComponent : Attribute { public RequireComponent(Type requiredComponent) { } }

    [AttributeUsage(AttributeTargets.Field)]
    public sealed class TooltipAttribute : Attribute { public TooltipAttribute(string tooltip) { } }
}

namespace UnityEngine.XR
{
    public enum XRNode { LeftEye, RightEye, CenterEye, Head, LeftHand, RightHand, GameController, TrackingReference, HardwareTracker }

    [Flags]
    public enum InputTrackingState : uint { None = 0, Position = 1, Rotation = 2, Velocity = 4, AngularVelocity = 8, Acceleration = 16, AngularAcceleration = 32, All = 63 }

    [Flags]
    public enum TrackingOriginModeFlags { Unknown = 0, Device = 1, Floor = 2, TrackingReference = 4, Unbounded = 8 }

    public struct InputFeatureUsage<T>
    {
        public InputFeatureUsage(string usageName) { }
    }

    public static class CommonUsages
    {
        public static InputFeatureUsage<InputTrackingState> trackingState;
        public static InputFeatureUsage<Vector3> devicePosition;
        public static InputFeatureUsage<Quaternion> deviceRotation;
        public static InputFeatureUsage<Vector3> centerEyePosition;
        public static InputFeatureUsage<Quaternion> centerEyeRotation;
    }

    public struct InputDevice
    {
        public bool isValid { get { return false; } }
        public bool TryGetFeatureValue(InputFeatureUsage<Vector3> usage, out Vector3 value) { value = default(Vector3); return false; }
        public bool TryGetFeatureValue(InputFeatureUsage<Quaternion> usage, out Quaternion value) { value = default(Quaternion); return false; }
        public bool TryGetFeatureValue(InputFeatureUsage<InputTrackingState> usage, out InputTrackingState value) { value = default(InputTrackingState); return false; }
    }

    public static class InputDevices
    {
        public static InputDevice GetDeviceAtXRNode(XRNode node) { return default(InputDevice); }
    }

    public class XRInputSubsystem : ISubsystem
    {
        public bool TrySetTrackingOriginMode(TrackingOriginModeFlags origin) { return false; }
    }
}
