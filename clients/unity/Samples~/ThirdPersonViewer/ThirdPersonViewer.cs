// Sample: a third-person viewer. Put it on a GameObject with an EgoPoseClient (role "render") and a
// SmplHumanoidDriver driving any humanoid avatar: it watches a session, lists the server's models as buttons
// that switch the session's model, and shows the session's state and the last calibration message.
//
// Needs UnityEngine (clients/unity/README.md, "Third-person viewer").
using System.Collections.Generic;
using EgoPose.Protocol;
using UnityEngine;

namespace EgoPose.Samples
{
    [RequireComponent(typeof(EgoPoseClient))]
    public sealed class ThirdPersonViewer : MonoBehaviour
    {
        EgoPoseClient client;
        readonly List<ModelInfo> models = new List<ModelInfo>();
        string status = "connecting";
        string calibration = "";
        Pose lastPose;

        void Awake()
        {
            client = GetComponent<EgoPoseClient>();
            if (client.role != "render") Debug.LogWarning("ThirdPersonViewer: set the EgoPoseClient's role to render");
            client.MessageReceived += OnMessage;
            client.PoseReceived += pose => lastPose = pose;
        }

        void OnMessage(Message message)
        {
            var list = message as Models;
            if (list != null)
            {
                models.Clear();
                models.AddRange(list.List);
            }
            var session = message as SessionStatus;
            if (session != null) status = session.Input ? "headset connected" : "waiting for the headset";
            var calibrated = message as Calibration;
            if (calibrated != null) calibration = calibrated.Status + ": " + calibrated.Text;
        }

        void OnGUI()
        {
            GUILayout.BeginArea(new Rect(10, 10, 360, 400));
            GUILayout.Label("session " + client.session + " (" + client.State + "): " + status);
            if (lastPose != null)
                GUILayout.Label("model " + lastPose.Model + ", pose " + lastPose.Seq + (lastPose.Camera == true ? ", camera" : ""));
            foreach (var info in models)
            {
                string label = (info.Name == client.ActiveModel ? "● " : "○ ") + info.Name + "  (" + string.Join("+", info.Inputs.ToArray()) + ")";
                if (GUILayout.Button(label)) client.SelectModel(info.Name);
            }
            if (GUILayout.Button("calibrate (T-pose, 2 s)")) client.Calibrate();
            if (calibration.Length > 0) GUILayout.Label(calibration);
            if (!string.IsNullOrEmpty(client.LastError)) GUILayout.Label("error: " + client.LastError);
            GUILayout.EndArea();
        }
    }
}
