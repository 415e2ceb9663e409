// One persistent WebSocket to an EgoPose server (PROTOCOL.md §1, §4): hello/welcome, a receive loop and a send
// loop off the caller's thread, reconnection with backoff that resumes the session (its model, and the wearer's
// body when one is given), and hand-over to the main thread (Unity's, or any other) through a latest-pose slot
// and a message queue.
//
//   var connection = new EgoPoseConnection(new ConnectionOptions { Url = "ws://host:8765/ws", Session = "room-1" });
//   connection.Start();
//   ... every frame:   connection.Send(hmd);  Pose pose; if (connection.TryTakePose(out pose)) Apply(pose);
//                      Message m; while (connection.TryDequeue(out m)) Handle(m);   // welcome, models, error, ...
//
// Pure C#: System.Net.WebSockets.ClientWebSocket, no UnityEngine. Thread-safe: Send, TryTakePose and TryDequeue
// may be called from any thread.
using System;
using System.Collections.Concurrent;
using System.Collections.Generic;
using System.Diagnostics;
using System.IO;
using System.Net.WebSockets;
using System.Threading;
using System.Threading.Tasks;

namespace EgoPose.Protocol
{
    public enum ConnectionState
    {
        Idle, // not started
        Connecting, // opening the socket or waiting for welcome
        Open, // welcomed: sending and receiving
        Waiting, // the connection dropped; reconnecting after a backoff
        Failed, // a fatal error that retrying cannot mend (auth_failed, a refused hello); see LastError
        Stopped,
    }

    public sealed class ConnectionOptions
    {
        public string Url = "ws://127.0.0.1:8765/ws"; // the session is added as ?session=
        public string Session = "default";
        public string Role = "input"; // "input" (the headset) or "render"
        public string Model; // optional: the model to start with
        public string Token; // optional shared secret
        public string ClientName = "egoposevr-unity/1.0";
        public TimeSpan MinBackoff = TimeSpan.FromMilliseconds(250);
        public TimeSpan MaxBackoff = TimeSpan.FromSeconds(5);
        public TimeSpan HandshakeTimeout = TimeSpan.FromSeconds(10);
        public int MaxMessageBytes = 8 * 1024 * 1024; // the server's default limit (§1)
        public int MaxPendingSends = 64; // a stalled network: beyond this, Send refuses hmd/rgbd (and counts them)
        public float[] Body; // optional: the wearer's kept body (21 bone lengths, m), given after every welcome (§4.2)
    }

    public sealed class EgoPoseConnection : IDisposable
    {
        // Codes after which a retry would only be refused again (PROTOCOL.md §6).
        static readonly string[] NotRetried = { "auth_failed", "invalid_field", "unsupported_version", "handshake_required" };

        readonly ConnectionOptions options;
        readonly ConcurrentQueue<Message> inbox = new ConcurrentQueue<Message>();
        readonly Queue<Message> outbox = new Queue<Message>(); // guarded by lock (outbox)
        readonly SemaphoreSlim outboxSignal = new SemaphoreSlim(0);
        readonly CancellationTokenSource stopping = new CancellationTokenSource();
        readonly Random jitter = new Random();
        Task runner;
        Pose latestPose;
        long latestTaken = -1;
        int state = (int)ConnectionState.Idle;
        string activeModel;
        float[] givenBody;

        public EgoPoseConnection(ConnectionOptions options)
        {
            this.options = options;
            activeModel = options.Model;
            if (options.Body != null) GiveBodyOnConnect(options.Body);
        }

        public ConnectionState State { get { return (ConnectionState)Volatile.Read(ref state); } }

        /// <summary>The welcome of the current (or last) connection.</summary>
        public Welcome Welcome { get; private set; }

        /// <summary>The last fatal error or connection failure, for the user.</summary>
        public string LastError { get; private set; }

        public long PosesReceived;
        public long Reconnects;

        /// <summary>hmd/rgbd dropped because the connection was down or the send queue was full.</summary>
        public long DroppedSends;

        /// <summary>The session's active model as the server last said (kept across reconnects).</summary>
        public string ActiveModel { get { return Volatile.Read(ref activeModel); } }

        /// <summary>
        /// The body given (<c>set_body</c>) as the first message after every welcome, before anything queued, so
        /// that every sample of a connection is served with it (§4.2); null: none. Takes effect at the next
        /// connection: send a <see cref="SetBody"/> as well to change the current session's. Forgotten when the
        /// server refuses it (<c>out_of_range</c>).
        /// </summary>
        public void GiveBodyOnConnect(float[] boneLengthsM)
        {
            if (boneLengthsM != null && boneLengthsM.Length != Body.BoneCount)
                throw new ArgumentException("a body holds " + Body.BoneCount + " bone lengths");
            Volatile.Write(ref givenBody, boneLengthsM == null ? null : (float[])boneLengthsM.Clone());
        }

        /// <summary>The body given after every welcome (<see cref="GiveBodyOnConnect"/>), or null.</summary>
        public float[] BodyGivenOnConnect { get { return Volatile.Read(ref givenBody); } }

        /// <summary>Microseconds on this process's monotonic clock, for <c>t_us</c>.</summary>
        public static long NowUs()
        {
            return (long)(Stopwatch.GetTimestamp() * (1e6 / Stopwatch.Frequency));
        }

        public void Start()
        {
            if (Interlocked.CompareExchange(ref state, (int)ConnectionState.Connecting, (int)ConnectionState.Idle)
                != (int)ConnectionState.Idle)
                throw new InvalidOperationException("already started");
            runner = Task.Run(() => RunAsync(stopping.Token));
        }

        /// <summary>
        /// Queue a message. hmd and rgbd are only worth sending now: while the connection is down they are
        /// dropped (false, counted in <see cref="DroppedSends"/>). Other messages wait for the next connection.
        /// </summary>
        public bool Send(Message message)
        {
            bool streamed = message is Hmd || message is Rgbd;
            if (streamed && State != ConnectionState.Open)
            {
                Interlocked.Increment(ref DroppedSends);
                return false;
            }
            lock (outbox)
            {
                if (streamed && outbox.Count >= options.MaxPendingSends)
                {
                    Interlocked.Increment(ref DroppedSends); // the network is stalled: newest data wins
                    return false;
                }
                outbox.Enqueue(message);
            }
            outboxSignal.Release();
            return true;
        }

        /// <summary>The newest pose received (taken or not); null before the first.</summary>
        public Pose LatestPose { get { return Volatile.Read(ref latestPose); } }

        /// <summary>The newest pose not taken before (older ones are superseded), for the render loop.</summary>
        public bool TryTakePose(out Pose pose)
        {
            pose = Volatile.Read(ref latestPose);
            if (pose == null || pose.Seq == Interlocked.Read(ref latestTaken)) return false;
            Interlocked.Exchange(ref latestTaken, pose.Seq);
            return true;
        }

        /// <summary>Every other server message (welcome, models, error, session, calibration, body, pong), in order.</summary>
        public bool TryDequeue(out Message message) { return inbox.TryDequeue(out message); }

        public async Task StopAsync()
        {
            stopping.Cancel();
            if (runner != null)
            {
                try { await runner.ConfigureAwait(false); }
                catch (OperationCanceledException) { }
            }
            Volatile.Write(ref state, (int)ConnectionState.Stopped);
        }

        public void Dispose()
        {
            StopAsync().Wait(TimeSpan.FromSeconds(5));
            stopping.Dispose();
        }

        async Task RunAsync(CancellationToken stop)
        {
            TimeSpan backoff = options.MinBackoff;
            while (!stop.IsCancellationRequested)
            {
                SetState(ConnectionState.Connecting);
                bool welcomed = false;
                try
                {
                    using (var socket = new ClientWebSocket())
                    {
                        welcomed = await ConnectAsync(socket, stop).ConfigureAwait(false);
                        if (welcomed)
                        {
                            backoff = options.MinBackoff;
                            DropStaleStreamed();
                            SetState(ConnectionState.Open);
                            await ServeAsync(socket, stop).ConfigureAwait(false);
                        }
                    }
                }
                catch (OperationCanceledException) when (stop.IsCancellationRequested)
                {
                    break;
                }
                catch (Exception exc) when (exc is WebSocketException || exc is IOException
                                            || exc is ProtocolException || exc is TimeoutException
                                            || exc is OperationCanceledException)
                {
                    LastError = exc.Message;
                }
                if (State == ConnectionState.Failed) return;
                if (stop.IsCancellationRequested) break;
                SetState(ConnectionState.Waiting);
                Interlocked.Increment(ref Reconnects);
                await Task.Delay(Jittered(backoff), stop).ConfigureAwait(false);
                backoff = TimeSpan.FromTicks(Math.Min(backoff.Ticks * 2, options.MaxBackoff.Ticks));
            }
        }

        /// <summary>Open the socket and say hello; true once welcomed.</summary>
        async Task<bool> ConnectAsync(ClientWebSocket socket, CancellationToken stop)
        {
            using (var timeout = CancellationTokenSource.CreateLinkedTokenSource(stop))
            {
                timeout.CancelAfter(options.HandshakeTimeout);
                var url = new Uri(options.Url + (options.Url.Contains("?") ? "&" : "?") + "session="
                                  + Uri.EscapeDataString(options.Session));
                await socket.ConnectAsync(url, timeout.Token).ConfigureAwait(false);
                var hello = new Hello
                {
                    Role = options.Role,
                    Session = options.Session,
                    Model = ActiveModel, // resume the session's model after a reconnect
                    Token = options.Token,
                    Client = options.ClientName,
                };
                await SendRawAsync(socket, hello.Encode(), timeout.Token).ConfigureAwait(false);
                while (true)
                {
                    var message = await ReceiveAsync(socket, timeout.Token).ConfigureAwait(false);
                    if (message == null) return false; // closed
                    Dispatch(message);
                    if (message is Welcome)
                    {
                        float[] body = BodyGivenOnConnect;
                        if (body != null)
                            await SendRawAsync(socket, new SetBody { BoneLengthsM = body }.Encode(), timeout.Token).ConfigureAwait(false);
                        return true;
                    }
                    var error = message as Error;
                    if (error != null && error.Fatal) return false;
                }
            }
        }

        async Task ServeAsync(ClientWebSocket socket, CancellationToken stop)
        {
            using (var connectionDone = CancellationTokenSource.CreateLinkedTokenSource(stop))
            {
                Task sending = SendLoopAsync(socket, connectionDone.Token);
                try
                {
                    while (true)
                    {
                        var message = await ReceiveAsync(socket, stop).ConfigureAwait(false);
                        if (message == null) break;
                        Dispatch(message);
                    }
                }
                finally
                {
                    connectionDone.Cancel();
                    try { await sending.ConfigureAwait(false); }
                    catch (OperationCanceledException) { }
                    catch (WebSocketException) { }
                }
            }
        }

        async Task SendLoopAsync(ClientWebSocket socket, CancellationToken done)
        {
            while (!done.IsCancellationRequested)
            {
                await outboxSignal.WaitAsync(done).ConfigureAwait(false);
                Message message;
                while ((message = PeekOutbox()) != null)
                {
                    await SendRawAsync(socket, message.Encode(), done).ConfigureAwait(false);
                    lock (outbox) outbox.Dequeue(); // only once sent: a message in flight at a drop is sent again
                }
            }
        }

        Message PeekOutbox()
        {
            lock (outbox) return outbox.Count > 0 ? outbox.Peek() : null;
        }

        /// <summary>Before a new connection opens: headset samples and frames queued for the old one are stale.</summary>
        void DropStaleStreamed()
        {
            lock (outbox)
            {
                var kept = new List<Message>();
                foreach (var message in outbox)
                {
                    if (message is Hmd || message is Rgbd) Interlocked.Increment(ref DroppedSends);
                    else kept.Add(message);
                }
                outbox.Clear();
                foreach (var message in kept) outbox.Enqueue(message);
                if (kept.Count > 0) outboxSignal.Release();
            }
        }

        static Task SendRawAsync(ClientWebSocket socket, byte[] data, CancellationToken token)
        {
            return socket.SendAsync(new ArraySegment<byte>(data), WebSocketMessageType.Binary, true, token);
        }

        /// <summary>The next message the client knows (unknown types are skipped, §8); null once closed.</summary>
        async Task<Message> ReceiveAsync(ClientWebSocket socket, CancellationToken token)
        {
            var buffer = new byte[64 * 1024];
            while (true)
            {
                using (var whole = new MemoryStream())
                {
                    WebSocketReceiveResult result;
                    do
                    {
                        result = await socket.ReceiveAsync(new ArraySegment<byte>(buffer), token).ConfigureAwait(false);
                        if (result.MessageType == WebSocketMessageType.Close)
                        {
                            await CloseQuietly(socket).ConfigureAwait(false);
                            return null;
                        }
                        whole.Write(buffer, 0, result.Count);
                        if (whole.Length > options.MaxMessageBytes)
                            throw new ProtocolException("a server message is over " + options.MaxMessageBytes + " bytes");
                    } while (!result.EndOfMessage);
                    if (result.MessageType != WebSocketMessageType.Binary) continue; // v1 sends binary only
                    var message = Protocol.DecodeFromServer(whole.GetBuffer(), 0, (int)whole.Length);
                    if (message != null) return message;
                }
            }
        }

        static async Task CloseQuietly(ClientWebSocket socket)
        {
            try
            {
                if (socket.State == WebSocketState.CloseReceived)
                    await socket.CloseOutputAsync(WebSocketCloseStatus.NormalClosure, "", CancellationToken.None)
                        .ConfigureAwait(false);
            }
            catch (WebSocketException) { }
        }

        void Dispatch(Message message)
        {
            var pose = message as Pose;
            if (pose != null)
            {
                Interlocked.Increment(ref PosesReceived);
                Volatile.Write(ref latestPose, pose);
                return;
            }
            var welcome = message as Welcome;
            if (welcome != null)
            {
                Welcome = welcome;
                Volatile.Write(ref activeModel, welcome.Model);
            }
            var models = message as Models;
            if (models != null) Volatile.Write(ref activeModel, models.Active);
            var error = message as Error;
            if (error != null && error.RefusesBody) Volatile.Write(ref givenBody, null); // not at every reconnect
            if (error != null && error.Fatal)
            {
                LastError = error.Code + ": " + error.Text;
                if (Array.IndexOf(NotRetried, error.Code) >= 0) SetState(ConnectionState.Failed);
            }
            inbox.Enqueue(message);
        }

        void SetState(ConnectionState value) { Volatile.Write(ref state, (int)value); }

        TimeSpan Jittered(TimeSpan delay)
        {
            double factor;
            lock (jitter) factor = 0.75 + 0.5 * jitter.NextDouble(); // spread many clients' retries apart
            return TimeSpan.FromTicks((long)(delay.Ticks * factor));
        }
    }
}
