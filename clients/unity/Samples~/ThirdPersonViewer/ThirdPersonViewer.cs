// Sample: a third-person viewer. Put it on a GameObject with an EgoPoseClient (role "render") and a
// SmplHumanoidDriver driving any humanoid avatar: it watches a session, lists the server's models as buttons
// that switch the session's model, and shows the session's state, the last calibration message and the wearer's
// body as the session knows it (given by the headset app, or estimated; PROTOCOL.md §4.2).
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
        string body = "";
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
            var known = message as Body;
            if (known != null)
            {
                // Joint 4 is the left knee: its bone is the thigh (the order of PROTOCOL.md §3).
                body = "body " + (known.Given ? "given" : "estimated") + (known.Measured ? ", measured" : "")
                       + ", thigh " + (100 * known.BoneLengthsM[3]).ToString("F1") + " cm";
            }
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
            if (GUILayout.Button("ask for the wearer's body")) client.Send(new GetBody());
            if (body.Length > 0) GUILayout.Label(body);
            if (!string.IsNullOrEmpty(client.LastError)) GUILayout.Label("error: " + client.LastError);
            GUILayout.EndArea();
        }
    }
}
