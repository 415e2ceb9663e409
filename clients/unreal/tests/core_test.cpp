// Checks EgoPoseProtocol.h against the protocol's golden fixtures and PROTOCOL.md's worked examples.
// Built and run by tests/clients/test_unreal_core.py: core_test GOLDEN_DIR OPENXR_DIR; exit 0 when all pass.
#include <cstdio>
#include <random>
#include <string>
#include <typeinfo>
#include <vector>

#include "../EgoPoseProtocol.h"
#include "checks.h"

using namespace egopose;

static void same_bytes(const std::string& expected, const msgpack::sbuffer& actual, const std::string& what) {
    check(expected == std::string(actual.data(), actual.size()), what + " gives the golden bytes");
}

static msgpack::object_handle read_message(const std::string& dir, const std::string& name, std::string& bytes) {
    bytes = read_file(dir + "/" + name + ".msgpack");
    auto handle = unpack(bytes.data(), bytes.size());
    check(message_type(handle) == name, name + " type");
    return handle;
}

static std::string repeat4(const std::string& part) { return part + part + part + part; }

// The bytes of a golden message with one field's value replaced.
static std::string with_field(const std::string& golden_bytes, const std::string& field, const msgpack::object& value) {
    auto handle = unpack(golden_bytes.data(), golden_bytes.size());
    msgpack::zone zone;
    msgpack::object root(handle.get(), zone);  // a deep copy whose field values can be swapped
    bool replaced = false;
    for (uint32_t i = 0; i < root.via.map.size; ++i)
        if (root.via.map.ptr[i].key.as<std::string>() == field) {
            root.via.map.ptr[i].val = value;
            replaced = true;
        }
    check(replaced, "the golden message has " + field);
    msgpack::sbuffer bytes;
    msgpack::pack(bytes, root);
    return {bytes.data(), bytes.size()};
}

// The reader must refuse the golden message with `field` set to `value`, naming the field.
template <typename Reader>
static void refuses_field(const std::string& golden_bytes, const std::string& field, const msgpack::object& value,
                          Reader read, const std::string& expected_in_message) {
    const std::string bytes = with_field(golden_bytes, field, value);
    std::string what = "(accepted)";
    try {
        read(unpack(bytes.data(), bytes.size()));
    } catch (const ProtocolError& exc) {
        what = exc.what();
    }
    check(what.find(expected_in_message) == 0, "a bad " + field + " is refused naming it (got \"" + what + "\")");
}

static void server_messages(const std::string& dir) {
    std::string bytes;
    Welcome welcome = read_welcome(read_message(dir, "welcome", bytes));
    check(welcome.session == "room-1" && welcome.role == "input" && welcome.server == "egoposevr/0.1.0" &&
              welcome.model == "egoposevr" && welcome.models == std::vector<std::string>{"egoposevr", "hmd"} &&
              !welcome.provider.has_value(),
          "welcome fields");
    refuses_field(bytes, "models", msgpack::object(7), read_welcome, "welcome.models: expected an array");

    Models models = read_models(read_message(dir, "models", bytes));
    check(models.active == "egoposevr" && models.models.size() == 2, "models: active and count");
    const ModelInfo& fusion = models.models[0];
    check(fusion.name == "egoposevr" && fusion.inputs == std::vector<std::string>{"hmd", "rgb", "depth"} &&
              fusion.description == "HMD + RGB-D fusion with KPO",
          "models[0] fields");
    check(fusion.sha256 == repeat4("0123456789abcdef") && fusion.encoder_sha256 == repeat4("fedcba9876543210"),
          "models[0] digests");
    check(models.models[1].name == "hmd" && !models.models[1].sha256 && !models.models[1].encoder_sha256,
          "models[1] has no digests");
    check(fusion.head_joint_m == std::array<float, 3>{0.0f, -0.0234375f, 0.0830078125f} && !models.models[1].head_joint_m,
          "models: the head joint where given (§model-head-joint)");
    refuses_field(bytes, "active", msgpack::object(true), read_models, "models.active: expected a string");

    SessionStatus session = read_session(read_message(dir, "session", bytes));
    check(session.session == "room-1" && session.event == "input_joined" && session.input &&
              session.model == "egoposevr" && session.renders == 2,
          "session fields");
    refuses_field(bytes, "renders", msgpack::object(1.5), read_session, "session.renders: wrong type");

    Calibration calibration = read_calibration(read_message(dir, "calibration", bytes));
    check(calibration.status == "done" && calibration.pose == "tpose" && calibration.head_height_m == 1.5f &&
              calibration.arm_span_m == 1.5f && calibration.corrections && (*calibration.corrections)[7] == 0.96875f,
          "calibration fields");
    const std::string nil_corrections = with_field(bytes, "corrections", msgpack::object());
    check(!read_calibration(unpack(nil_corrections.data(), nil_corrections.size())).corrections,
          "a nil optional reads as absent");
    refuses_field(bytes, "corrections", msgpack::object(1), read_calibration,
                  "calibration.corrections: expected an array");

    Pong pong = read_pong(read_message(dir, "pong", bytes));
    check(pong.nonce == 3 && pong.t_us == 1000900 && pong.server_t_us == 5000000123LL, "pong fields");

    read_pose(read_message(dir, "pose", bytes));
    refuses_field(bytes, "joints", msgpack::object(), read_pose, "pose.joints: missing");
    refuses_field(bytes, "seq", msgpack::object(1.5), read_pose, "pose.seq: wrong type");
    refuses_field(bytes, "model", msgpack::object(3), read_pose, "pose.model: expected a string");
    refuses_field(bytes, "planted", msgpack::object(1), read_pose, "pose.planted: expected an array");
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
    same_bytes(read_file(dir + "/list_models.msgpack"), encode(ListModels{}), "list_models");
    same_bytes(read_file(dir + "/ping.msgpack"), encode(Ping{3, 1000900}), "ping");
    // The golden rgbd's JPEG and PNG bytes, taken from the file as a camera app would take its encoder's output.
    const std::string rgbd_bytes = read_file(dir + "/rgbd.msgpack");
    auto rgbd_handle = unpack(rgbd_bytes.data(), rgbd_bytes.size());
    const detail::Fields rgbd_fields(rgbd_handle.get(), "rgbd");
    Rgbd rgbd;
    rgbd.seq = 7;
    rgbd.t_us = 1000500;
    rgbd.width = 4;
    rgbd.height = 2;
    rgbd.intrinsics = {2, 2, 2, 1};
    rgbd.rgb = rgbd_fields.required("rgb").as<std::string>();
    rgbd.depth = rgbd_fields.required("depth").as<std::string>();
    rgbd.cam_from_head = std::array<float, 16>{1, 0, 0, 0, 0, 0, 1, 0.125f, 0, -1, 0, -0.0625f, 0, 0, 0, 1};
    same_bytes(rgbd_bytes, encode(rgbd), "rgbd");
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
    check(pose.planted.has_value() && (*pose.planted)[0] && !(*pose.planted)[1] && pose.floor_y_m == 0.0f,
          "pose: which feet are planted and the floor (§planted-feet)");

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

// Reads a server message as a client would: its type, then that type's reader.
static void read_any(const std::string& bytes) {
    auto handle = unpack(bytes.data(), bytes.size());
    const std::string type = message_type(handle);
    if (type == "welcome") read_welcome(handle);
    if (type == "pose") read_pose(handle);
    if (type == "models") read_models(handle);
    if (type == "error") read_error(handle);
    if (type == "session") read_session(handle);
    if (type == "calibration") read_calibration(handle);
    if (type == "body") read_body(handle);
    if (type == "pong") read_pong(handle);
}

// Every golden server message damaged many ways (bytes changed, cut short, grown): each reads or is refused with
// a ProtocolError; any other exception (a msgpack type error escaping, a bad_alloc) fails.
static void damaged_messages(const std::string& dir) {
    uint64_t state = 12345;
    auto next = [&state]() {  // a fixed xorshift: the same damage on every run
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        return state;
    };
    int refused = 0, read = 0;
    for (const char* name : {"welcome", "pose", "models", "error", "session", "calibration", "body", "pong"}) {
        const std::string golden_bytes = read_file(dir + "/" + name + ".msgpack");
        for (int trial = 0; trial < 3000; ++trial) {
            std::string bytes = golden_bytes;
            const int kind = static_cast<int>(next() % 3);
            if (kind == 0 || bytes.empty()) {
                for (int k = 0; k < 1 + static_cast<int>(next() % 4); ++k)
                    bytes[next() % bytes.size()] = static_cast<char>(next());
            } else if (kind == 1) {
                bytes.resize(next() % bytes.size());
            } else {
                bytes.insert(next() % bytes.size(), 1 + next() % 8, static_cast<char>(next()));
            }
            try {
                read_any(bytes);
                ++read;
            } catch (const ProtocolError&) {
                ++refused;
            } catch (const std::exception& exc) {
                throw std::runtime_error(std::string(name) + " damaged (trial " + std::to_string(trial) +
                                         ") escaped as " + typeid(exc).name() + ": " + exc.what());
            }
        }
    }
    check(refused > 1000 && read > 100, "damaged messages: " + std::to_string(refused) + " refused, " +
                                            std::to_string(read) + " still read");
}

// FootPins (PROTOCOL.md §planted-feet), as the Unity package's tests check its own: the two-bone reach puts the foot
// on a target within reach with the bones' lengths kept and the knee bent on its own side, straightens towards one
// out of reach, bends a straight leg to the body's front, and the pins follow `planted`, a pause and a far hip.
static Vec3 bend_of(const Vec3& hip, const Vec3& knee, const Vec3& ankle) {  // the knee's way off the hip-ankle line
    return detail::across(detail::sub(knee, hip), detail::unit(detail::sub(ankle, hip)));
}

static void foot_pins() {
    using namespace detail;
    std::mt19937_64 rng(3);  // the same legs on every run
    std::uniform_real_distribution<double> within(-1.0, 1.0), share(0.0, 1.0);
    auto noise = [&](double scale) { return within(rng) * scale; };
    for (int trial = 0; trial < 200; ++trial) {
        const Vec3 hip{noise(1), 1 + noise(0.1), noise(1)};
        const Vec3 knee{hip.x + noise(0.15), hip.y - 0.42 + noise(0.05), hip.z + noise(0.15)};
        const Vec3 ankle{knee.x + noise(0.2), knee.y - 0.4 + noise(0.05), knee.z + 0.1 + noise(0.1)};
        const double thigh = norm(sub(knee, hip)), shin = norm(sub(ankle, knee));
        const bool far = trial % 4 == 3;
        Vec3 way = sub(ankle, hip);
        way = {way.x + noise(0.2), way.y, way.z + noise(0.2)};
        const double span = far ? thigh + shin + 0.3 : (0.6 + 0.38 * share(rng)) * (thigh + shin);
        const Vec3 target = add(hip, scaled(way, span / norm(way)));
        const auto turns = FootPins::reach(hip, knee, ankle, target, {0, 0, 1});
        const Vec3 new_knee = add(hip, rotate(turns.thigh, sub(knee, hip)));
        const Vec3 shin_now = rotate(turns.thigh, rotate(turns.knee, sub(ankle, knee)));
        const Vec3 new_ankle = add(new_knee, shin_now);
        const std::string at = " (trial " + std::to_string(trial) + ")";
        check(std::abs(norm(sub(new_knee, hip)) - thigh) < 1e-9 && std::abs(norm(shin_now) - shin) < 1e-9,
              "the reach keeps the bones' lengths" + at);
        const Vec3 before = bend_of(hip, knee, ankle), after = bend_of(hip, new_knee, new_ankle);
        if (norm(before) > 0.12 && norm(after) > 0.02)  // farther off the line than the front's pull
            check(dot(before, rotate(turns.thigh, before)) > 0 && dot(rotate(turns.thigh, before), after) > 0,
                  "the knee bends on the side it bent" + at);
        if (!far) {
            check(norm(sub(new_ankle, target)) < 1e-6, "a target within reach is reached" + at);
        } else {
            const Vec3 along = sub(target, hip), reached = sub(new_ankle, hip);
            check(std::abs(norm(reached) - (thigh + shin)) < 2e-3 &&
                      dot(reached, along) / (norm(reached) * norm(along)) > 0.9999,
                  "a target out of reach straightens the leg towards it" + at);
        }
    }
    for (double front : {1.0, -1.0}) {
        const Vec3 hip{0, 1, 0}, knee{0, 0.55, 0.001}, ankle{0, 0.1, 0}, lower{0, 0.25, 0};
        const auto turns = FootPins::reach(hip, knee, ankle, lower, {0, 0, front});
        const Vec3 bent_knee = add(hip, rotate(turns.thigh, sub(knee, hip)));
        check(bent_knee.z * front > 0.1, "a straight leg whose hips come down bends its knee to the body's front");
    }
    FootPins pins;
    const Vec3 landed{0.1, 0.03, 0.2}, hip{0.1, 0.9, 0.1}, moved{0.3, 0.03, 0.2};
    check(!pins.target(0, true, 0, hip, landed, 0.85), "a foot that lands stays where the pose put it");
    check(!pins.target(1, false, 0, hip, landed, 0.85), "a free foot has no pin");
    const auto pin = pins.target(0, true, 11111, hip, moved, 0.85);
    check(pin && pin->x == landed.x && pin->y == landed.y && pin->z == landed.z,
          "while planted, the foot is held where it landed");
    check(!pins.target(0, true, 22222, {5, 0.9, 0}, moved, 0.85),
          "a pin out of the leg's reach (a recentred space) is dropped and the foot lands anew");
    check(!pins.target(0, false, 33333, hip, moved, 0.85), "a foot let go is free");
    pins.target(0, true, 44444, hip, landed, 0.85);
    check(!pins.target(0, true, 44444 + FootPins::kGapUs + 1, hip, moved, 0.85), "after a pause the foot lands anew");
}

int main(int argc, char** argv) {
    if (argc != 3) {
        std::fprintf(stderr, "usage: core_test GOLDEN_DIR OPENXR_DIR\n");
        return 2;
    }
    try {
        golden(argv[1]);
        server_messages(argv[1]);
        damaged_messages(argv[1]);
        openxr_from_unreal(argv[2]);
        foot_pins();
    } catch (const std::exception& exc) {
        std::printf("FAILED: %s\n", exc.what());
        return 1;
    }
    std::printf("ok: %d checks\n", checks);
    return 0;
}
