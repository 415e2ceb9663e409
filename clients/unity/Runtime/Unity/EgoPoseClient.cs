// The scene's connection to an EgoPose server: a MonoBehaviour around Core/EgoPoseConnection.cs that hands the
// newest pose and every other server message to Unity's main thread once per frame, and (for the headset) keeps
// the wearer's measured body in PlayerPrefs between sessions (Core/BodyKeeper.cs, PROTOCOL.md §4.2).
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

        [Tooltip("Input role: the PlayerPrefs key under which the wearer's measured body is kept and given back at the next session (one per wearer); empty: none kept")]
        public string bodyKey = "EgoPose.body";

        [Tooltip("While the session estimates the wearer's body, ask the server for it this often (s)")]
        public float askBodyEverySeconds = 15f;

        EgoPoseConnection connection;
        BodyKeeper bodyKeeper;

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

        /// <summary>The wearer's kept body (21 bone lengths, m) given at every connection, or null while none is.</summary>
        public float[] KeptBody { get { return bodyKeeper == null ? null : bodyKeeper.Kept; } }

        bool KeepsBody { get { return role == "input" && !string.IsNullOrEmpty(bodyKey); } }

        void OnEnable()
        {
            bodyKeeper = KeepsBody ? new BodyKeeper(BodyKeeper.Parse(PlayerPrefs.GetString(bodyKey, "")), askBodyEverySeconds) : null;
            connection = new EgoPoseConnection(new ConnectionOptions
            {
                Url = url,
                Session = session,
                Role = role,
                Model = string.IsNullOrEmpty(model) ? null : model,
                Token = string.IsNullOrEmpty(token) ? null : token,
                ClientName = "unity/" + Application.unityVersion + " " + SystemInfo.deviceModel,
                Body = KeptBody,
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
                if (bodyKeeper != null && bodyKeeper.Take(message)) StoreKeptBody();
                if (MessageReceived != null) MessageReceived(message);
            }
            if (bodyKeeper != null && connection.State == ConnectionState.Open)
            {
                var ask = bodyKeeper.Poll(Time.unscaledTime);
                if (ask != null) Send(ask);
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

        /// <summary>
        /// Forget the kept body (another wearer puts the headset on): deleted from PlayerPrefs, the session
        /// estimates the body again, and the next measured one is kept.
        /// </summary>
        public void ForgetBody()
        {
            if (bodyKeeper == null) return;
            Send(bodyKeeper.Forget());
            StoreKeptBody();
        }

        void StoreKeptBody()
        {
            float[] kept = bodyKeeper.Kept;
            if (kept == null) PlayerPrefs.DeleteKey(bodyKey);
            else PlayerPrefs.SetString(bodyKey, BodyKeeper.Format(kept));
            PlayerPrefs.Save();
            if (connection != null) connection.GiveBodyOnConnect(kept);
        }
    }
}
