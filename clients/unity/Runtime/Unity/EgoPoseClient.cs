// The scene's connection to an EgoPose server: a MonoBehaviour around Core/EgoPoseConnection.cs that hands the
// newest pose and every other server message to Unity's main thread once per frame.
//
// Needs UnityEngine: not compiled by the project's tests (the Core it wraps is; clients/unity/README.md).
using System;
using EgoPose.Protocol;
using UnityEngine;

namespace EgoPose
{
    [AddComponentMenu("EgoPose/EgoPose Client")]
    public sealed class EgoPoseClient : MonoBehaviour
    {
        [Tooltip("ws://HOST:PORT/ws of the EgoPose server (wss:// behind TLS)")]
        public string url = "ws://127.0.0.1:8765/ws";

        [Tooltip("Clients of one session share its poses (name: letters, digits, _ . : -)")]
        public string session = "default";

        [Tooltip("input: this app is the headset; render: it only watches a session")]
        public string role = "input";

        [Tooltip("Model to start with; empty: the session's (or the server's default)")]
        public string model = "";

        [Tooltip("Shared secret, when the server requires one")]
        public string token = "";

        EgoPoseConnection connection;

        /// <summary>The newest pose, updated at the start of each frame on the main thread.</summary>
        public Pose LatestPose { get; private set; }

        /// <summary>Raised on the main thread for each new pose.</summary>
        public event Action<Pose> PoseReceived;

        /// <summary>Raised on the main thread for every other server message (models, error, calibration, ...).</summary>
        public event Action<Message> MessageReceived;

        public ConnectionState State { get { return connection == null ? ConnectionState.Idle : connection.State; } }

        public string ActiveModel { get { return connection == null ? null : connection.ActiveModel; } }

        /// <summary>The last fatal error or connection failure, for the user.</summary>
        public string LastError { get { return connection == null ? null : connection.LastError; } }

        void OnEnable()
        {
            connection = new EgoPoseConnection(new ConnectionOptions
            {
                Url = url,
                Session = session,
                Role = role,
                Model = string.IsNullOrEmpty(model) ? null : model,
                Token = string.IsNullOrEmpty(token) ? null : token,
                ClientName = "unity/" + Application.unityVersion + " " + SystemInfo.deviceModel,
            });
            connection.Start();
        }

        void OnDisable()
        {
            if (connection == null) return;
            connection.Dispose();
            connection = null;
        }

        void Update()
        {
            if (connection == null) return;
            Message message;
            while (connection.TryDequeue(out message))
            {
                var error = message as Error;
                if (error != null) Debug.LogWarning("EgoPose: " + error.Code + ": " + error.Text);
                if (MessageReceived != null) MessageReceived(message);
            }
            Pose pose;
            if (connection.TryTakePose(out pose))
            {
                LatestPose = pose;
                if (PoseReceived != null) PoseReceived(pose);
            }
        }

        /// <summary>Queue a message (false: an hmd/rgbd dropped because the connection is down).</summary>
        public bool Send(Message message)
        {
            return connection != null && connection.Send(message);
        }

        public void SelectModel(string name) { Send(new SelectModel { Model = name }); }

        public void ListModels() { Send(new ListModels()); }

        /// <summary>Ask the server to measure the wearer (PROTOCOL.md §4.1). Tell the user what to do first.</summary>
        public void Calibrate(string pose = "tpose", float seconds = 2f) { Send(new Calibrate { Pose = pose, Seconds = seconds }); }

        public void ClearCalibration() { Send(new Calibrate { Clear = true }); }
    }
}
