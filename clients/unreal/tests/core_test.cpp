// Checks EgoPoseProtocol.h against the protocol's golden fixtures and PROTOCOL.md's worked examples.
// Built and run by tests/clients/test_unreal_core.py: core_test GOLDEN_DIR OPENXR_DIR; exit 0 when all pass.
#include <cstdio>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "../EgoPoseProtocol.h"

using namespace egopose;

static int checks = 0;

static void check(bool ok, const std::string& what) {
    ++checks;
    if (!ok) throw std::runtime_error("check failed: " + what);
}

static std::string read_file(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw std::runtime_error("cannot read " + path);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

static void same_bytes(const std::string& expected, const msgpack::sbuffer& actual, const std::string& what) {
    check(expected == std::string(actual.data(), actual.size()), what + " gives the golden bytes");
}

static void golden(const std::string& dir) {
    same_bytes(read_file(dir + "/hello.msgpack"),
               encode(Hello{"input", "room-1", "egoposevr", "s3cret", "unity/1.0"}), "hello");
    const float half = 0.7071067690849304f;
    Hmd hmd;
    hmd.seq = 42;
    hmd.t_us = 1000000;
    hmd.head = {0, 1.625f, 0, 0, 0, 0, 1};
    hmd.left = {-0.25f, 1, -0.25f, 0, 0, 0, 1};
    hmd.right = {0.25f, 1, -0.25f, 0, half, 0, half};
    hmd.valid = {true, true, false};
    same_bytes(read_file(dir + "/hmd.msgpack"), encode(hmd), "hmd");
    same_bytes(read_file(dir + "/select_model.msgpack"), encode(SelectModel{"hmd"}), "select_model");
    same_bytes(read_file(dir + "/calibrate.msgpack"), encode(Calibrate{"tpose", 2.0f, false}), "calibrate");
    same_bytes(read_file(dir + "/get_body.msgpack"), encode(GetBody{}), "get_body");
    // protocol/examples.py's body: near the mean body's, in 1/16 m steps
    const BoneLengths lengths{0.125f, 0.125f, 0.125f, 0.375f, 0.375f, 0.125f, 0.4375f, 0.4375f, 0.0625f, 0.125f, 0.125f,
                              0.1875f, 0.125f, 0.125f, 0.125f, 0.125f, 0.125f, 0.25f, 0.25f, 0.25f, 0.25f};
    same_bytes(read_file(dir + "/set_body.msgpack"), encode(SetBody{lengths, false}), "set_body");
    const char clear_only[] = "\x83\xa4" "type" "\xa8" "set_body" "\xa1" "v" "\x01\xa5" "clear" "\xc3";
    same_bytes(std::string(clear_only, sizeof clear_only - 1), encode(SetBody{std::nullopt, true}),
               "set_body clear, without lengths");
    for (const SetBody& bad : {SetBody{std::nullopt, false}, SetBody{lengths, true}}) {
        bool refused = false;
        try {
            encode(bad);
        } catch (const std::invalid_argument&) {
            refused = true;
        }
        check(refused, "set_body with neither lengths nor clear, or both, is refused");
    }

    std::string bytes = read_file(dir + "/pose.msgpack");
    auto handle = unpack(bytes.data(), bytes.size());
    check(message_type(handle) == "pose", "pose type");
    Pose pose = read_pose(handle);
    check(pose.seq == 42 && pose.t_us == 1000000 && pose.model == "egoposevr", "pose header fields");
    check(pose.body_pose[9] == 0.5f && pose.global_orient[1] == 3.125f && pose.transl[1] == 0.875f, "pose numbers");
    check(pose.timing_us.at("fusion") == 900 && !pose.camera.has_value(), "pose timing and optionals");

    bytes = read_file(dir + "/error.msgpack");
    auto error_handle = unpack(bytes.data(), bytes.size());
    Error error = read_error(error_handle);
    check(message_type(error_handle) == "error" && error.code == "wrong_length" && !error.fatal, "error fields");
    check(error.ref_type == std::optional<std::string>("hmd"), "error.ref names the message that caused it");

    bytes = read_file(dir + "/body.msgpack");
    auto body_handle = unpack(bytes.data(), bytes.size());
    Body body = read_body(body_handle);
    check(message_type(body_handle) == "body" && body.bone_lengths_m == lengths && body.given && !body.measured,
          "body fields");

    for (std::string bad : {std::string("\x81\xa4", 2), std::string("\x90\x90", 2), std::string("\x93\x01\x02\x03", 4)}) {
        bool refused = false;
        try {
            auto h = unpack(bad.data(), bad.size());
            message_type(h);
        } catch (const ProtocolError&) {
            refused = true;
        }
        check(refused, "malformed bytes are refused");
    }
}

// PROTOCOL.md §3.3's first walk-through, reached from Unreal's tracking space (cm, FQuat) instead of OpenXR.
static void openxr_from_unreal(const std::string& dir) {
    const double half = 0.7071067690849304;
    Vec3 head_cm = to_unreal_position(0, 1.625, 0);
    Vec3 left_cm = to_unreal_position(-0.25, 1, -0.25);
    Vec3 right_cm = to_unreal_position(0.25, 1, -0.25);
    Quat identity = to_unreal_rotation({0, 0, 0, 1});
    Quat right_turned = to_unreal_rotation({0, half, 0, half});
    check(right_turned.x == 0 && right_turned.y == 0 && right_turned.z == -half && right_turned.w == half,
          "§3.2's example: a quarter turn about +Y becomes (0, 0, -0.7071, 0.7071) in Unreal");
    Hmd hmd;
    hmd.seq = 7;
    hmd.t_us = 2000000;
    hmd.head = pose_from_unreal(head_cm, identity);
    hmd.left = controller_from_grip(from_unreal_position(left_cm), from_unreal_rotation(identity), true);
    hmd.right = controller_from_grip(from_unreal_position(right_cm), from_unreal_rotation(right_turned), false);
    hmd.valid = {true, true, true};
    same_bytes(read_file(dir + "/openxr-tracked.msgpack"), encode(hmd), "openxr-tracked from Unreal's frame");
}

int main(int argc, char** argv) {
    if (argc != 3) {
        std::fprintf(stderr, "usage: core_test GOLDEN_DIR OPENXR_DIR\n");
        return 2;
    }
    try {
        golden(argv[1]);
        openxr_from_unreal(argv[2]);
    } catch (const std::exception& exc) {
        std::printf("FAILED: %s\n", exc.what());
        return 1;
    }
    std::printf("ok: %d checks\n", checks);
    return 0;
}
