// A scripted input client of EgoPoseProtocol.h against a real server: every message it sends is the core's encoding
// and every message it reads goes through the core's readers. The socket is tests/clients/test_unreal_core.py's:
// it relays each WebSocket message as a 4-byte big-endian length and the bytes, server -> stdin, stdout -> server.
// Usage: live_client RGB.jpg DEPTH.png; prints "ok: N checks" on stderr and exits 0 when all pass.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "../EgoPoseProtocol.h"
#include "checks.h"

using namespace egopose;

static void send(const msgpack::sbuffer& message) {
    const uint32_t n = static_cast<uint32_t>(message.size());
    const unsigned char header[4] = {static_cast<unsigned char>(n >> 24), static_cast<unsigned char>(n >> 16),
                                     static_cast<unsigned char>(n >> 8), static_cast<unsigned char>(n)};
    if (std::fwrite(header, 1, 4, stdout) != 4 || std::fwrite(message.data(), 1, n, stdout) != n)
        throw std::runtime_error("the relay stopped reading");
    std::fflush(stdout);
}

// One server message: its bytes, unpacked, and its type.
struct Received {
    std::string bytes;
    msgpack::object_handle handle;
    std::string type;
};

static Received receive() {
    unsigned char header[4];
    if (std::fread(header, 1, 4, stdin) != 4) throw std::runtime_error("the connection closed");
    const uint32_t n = uint32_t(header[0]) << 24 | uint32_t(header[1]) << 16 | uint32_t(header[2]) << 8 | header[3];
    Received message;
    message.bytes.resize(n);
    if (n > 0 && std::fread(&message.bytes[0], 1, n, stdin) != n) throw std::runtime_error("a message was cut off");
    message.handle = unpack(message.bytes.data(), message.bytes.size());
    message.type = message_type(message.handle);
    return message;
}

// The next message of `type` that `accept` takes, skipping the others (poses stream in between).
template <typename Accept>
static Received receive_until(const std::string& type, Accept accept, const std::string& what) {
    for (int skipped = 0; skipped < 5000; ++skipped) {
        Received message = receive();
        if (message.type == "error" && type != "error") {
            const Error error = read_error(message.handle);
            throw std::runtime_error("unexpected error while waiting for " + what + ": " + error.code + ": " +
                                     error.message);
        }
        if (message.type == type && accept(message)) return message;
    }
    throw std::runtime_error("never received " + what);
}

static Received receive_type(const std::string& type) {
    return receive_until(type, [](const Received&) { return true; }, type);
}

static Hmd standing_sample(int64_t seq) {
    Hmd hmd;
    hmd.seq = seq;
    hmd.t_us = 1000000 + seq * 11111;  // 90 Hz
    hmd.head = {0, 1.6f, 0, 0, 0, 0, 1};
    hmd.left = {-0.3f, 1.0f, -0.1f, 0, 0, 0, 1};
    hmd.right = {0.3f, 1.0f, -0.1f, 0, 0, 0, 1};
    return hmd;
}

// `count` headset samples from `first` at 90 Hz, and a camera frame with every third.
static void stream(const Rgbd& frame, int64_t first, int64_t count) {
    for (int64_t seq = first; seq < first + count; ++seq) {
        const Hmd hmd = standing_sample(seq);
        send(encode(hmd));
        if (seq % 3 == 0) {
            Rgbd rgbd = frame;
            rgbd.seq = seq / 3;
            rgbd.t_us = hmd.t_us;
            send(encode(rgbd));
        }
        std::this_thread::sleep_for(std::chrono::microseconds(11111));
    }
}

static bool is_digest(const std::optional<std::string>& text) {
    if (!text || text->size() != 64) return false;
    for (char c : *text)
        if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
    return true;
}

static void live(const std::string& rgb_path, const std::string& depth_path) {
    send(encode(Hello{"input", "cpp-live", "egoposevr", std::nullopt, std::string("cpp-core-test/1")}));
    const Welcome welcome = read_welcome(receive_type("welcome").handle);
    check(welcome.session == "cpp-live" && welcome.role == "input" && welcome.model == "egoposevr",
          "welcome names the session, the role and the model");
    check(welcome.server.rfind("egoposevr/", 0) == 0 && welcome.provider.has_value(), "welcome names the server");
    const Models models = read_models(receive_type("models").handle);
    check(models.active == "egoposevr" && models.models.size() == welcome.models.size(),
          "models lists every model the welcome named");
    for (const ModelInfo& info : models.models) {
        check(!info.inputs.empty() && info.inputs[0] == "hmd", info.name + " reads the headset");
        if (info.name == "procedural") {
            check(!info.sha256 && !info.encoder_sha256, "a model that is code names no file (§model-digests)");
        } else {
            check(is_digest(info.sha256), info.name + " names the file it serves");
            const bool camera = info.inputs.size() > 1;
            check(camera ? is_digest(info.encoder_sha256) : !info.encoder_sha256,
                  info.name + " names an encoder exactly when it reads a camera");
        }
        check(info.head_joint_m == std::array<float, 3>{0.0f, -0.024f, 0.083f},
              info.name + " hangs the head joint where every bundled model does (§model-head-joint)");
    }

    send(encode(Ping{11, 123}));
    const Pong pong = read_pong(receive_until("pong", [](const Received&) { return true; }, "pong").handle);
    check(pong.nonce == 11 && pong.t_us == 123 && pong.server_t_us > 0, "pong echoes the ping");

    Rgbd frame;
    frame.width = 160;
    frame.height = 128;
    frame.intrinsics = {80, 80, 80, 64};
    frame.rgb = read_file(rgb_path);
    frame.depth = read_file(depth_path);
    // A busy server answers samples before it has read the first frame without it (§frames): stream until one
    // used the camera, as a headset does.
    Pose pose;
    int64_t next = 0;
    for (int tries = 0; tries < 10 && pose.camera != true; ++tries, next += 45) {
        stream(frame, next, 45);
        const int64_t last = next + 44;
        pose = read_pose(
            receive_until("pose", [&](const Received& m) { return read_pose(m.handle).seq == last; }, "the last pose")
                .handle);
    }
    check(pose.camera == true && pose.model == "egoposevr", "the fusion model used the camera");
    check(pose.t_us == standing_sample(pose.seq).t_us, "pose.t_us answers its hmd");
    for (float value : pose.joints) check(std::isfinite(value), "joints are finite");
    // The headset at (0, 1.6, 0) looks along -Z unturned, so the head joint is there plus the model's head_joint_m.
    std::array<float, 3> hung{};
    for (const ModelInfo& info : models.models)
        if (info.name == pose.model) hung = info.head_joint_m.value_or(hung);  // none: fails below
    const double head_off_cm = 100 * std::hypot(pose.joints[3 * 15] - hung[0], pose.joints[3 * 15 + 1] - (1.6 + hung[1]),
                                                pose.joints[3 * 15 + 2] - hung[2]);
    check(head_off_cm < 4, "the head joint hangs where head_joint_m says: " + std::to_string(head_off_cm) + " cm off");

    send(encode(SelectModel{"procedural"}));
    const Models switched = read_models(
        receive_until("models", [](const Received& m) { return read_models(m.handle).active == "procedural"; },
                      "models after select_model")
            .handle);
    check(switched.active == "procedural", "select_model is answered by models");
    stream(frame, next, 3);
    const Pose procedural = read_pose(
        receive_until("pose", [&](const Received& m) { return read_pose(m.handle).seq == next + 2; }, "a pose")
            .handle);
    check(procedural.model == "procedural" && !procedural.camera.has_value(), "the new model answers");
    next += 3;

    send(encode(ListModels{}));
    check(read_models(receive_type("models").handle).active == "procedural", "list_models names the active model");

    send(encode(GetBody{}));
    const Body body = read_body(receive_type("body").handle);
    check(!body.given && body.bone_lengths_m[3] > 0.2f && body.bone_lengths_m[3] < 0.7f,
          "get_body gives the session's estimate");

    send(encode(Calibrate{"stand", 1.0f, false}));
    const Calibration started = read_calibration(receive_type("calibration").handle);
    check(started.status == "started" && started.pose == "stand" && !started.message.empty(),
          "calibrate is answered by calibration started");
    stream(frame, next, 135);  // 1.5 s of a still stander: the measurement lasts 1 s of t_us
    next += 135;
    const Calibration done = read_calibration(receive_type("calibration").handle);
    check(done.status == "done" && done.head_height_m && *done.head_height_m > 1.45f && *done.head_height_m < 1.6f,
          "a still stander is measured: head joint " + std::to_string(done.head_height_m.value_or(0)) + " m");
    check(done.corrections && !done.arm_span_m, "stand measures the headset, not the arms");
    send(encode(Calibrate{"stand", 1.0f, true}));
    check(read_calibration(receive_type("calibration").handle).status == "cleared", "clear forgets it");

    Hmd bad = standing_sample(next);
    bad.head[6] = 2;  // not a unit quaternion
    send(encode(bad));
    const Error error = read_error(receive_type("error").handle);
    check(error.code == "bad_quaternion" && !error.fatal && error.ref_type == std::optional<std::string>("hmd"),
          "a bad sample is refused naming it, and the session goes on");
    send(encode(Ping{12, std::nullopt}));
    check(read_pong(receive_type("pong").handle).nonce == 12, "the session still answers");
}

int main(int argc, char** argv) {
    if (argc != 3) {
        std::fprintf(stderr, "usage: live_client RGB.jpg DEPTH.png\n");
        return 2;
    }
    try {
        live(argv[1], argv[2]);
    } catch (const std::exception& exc) {
        std::fprintf(stderr, "FAILED after %d checks: %s\n", checks, exc.what());
        return 1;
    }
    std::fprintf(stderr, "ok: %d checks\n", checks);
    return 0;
}
