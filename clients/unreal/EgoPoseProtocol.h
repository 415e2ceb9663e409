// EgoPose protocol v1 for C++ (PROTOCOL.md): every message a C++ client sends (an Unreal headset, a camera
// app, a render client) and every message the server sends it, with msgpack-c (msgpack-cxx, header-only), and
// the frame conversions of §3.2. A server message that breaks the schema throws ProtocolError naming the field.
//
// Plain C++17 and msgpack-cxx, no Unreal types: tests/clients/test_unreal_core.py compiles it with g++ and checks
// it against the golden fixtures and, as a scripted client, a real server. EgoPoseComponent.h/.cpp is the Unreal
// side that uses it.
//
// Frames: the protocol's world is right-handed, +Y up, -Z forward, metres; quaternions (x, y, z, w). Unreal's is
// left-handed, +Z up, +X forward, +Y right, centimetres.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#define MSGPACK_NO_BOOST
#include <msgpack.hpp>

namespace egopose {

using Pose7 = std::array<float, 7>;  // [px, py, pz, qx, qy, qz, qw], protocol frame

struct Hello {
    std::string role = "input";  // "input" or "render"
    std::string session;
    std::optional<std::string> model, token, client;
};

struct Hmd {
    int64_t seq = 0;
    int64_t t_us = 0;  // microseconds on the sender's monotonic clock
    Pose7 head{0, 0, 0, 0, 0, 0, 1}, left{0, 0, 0, 0, 0, 0, 1}, right{0, 0, 0, 0, 0, 0, 1};
    std::array<bool, 3> valid{true, true, true};  // head, left, right: position and orientation known
};

struct SelectModel {
    std::string model;
};

// One egocentric RGB-D frame (§5 rgbd): JPEG colour and 16-bit PNG depth in millimetres (0 = no reading), both
// width x height; the bytes are sent as they are (the server checks their signatures and sizes).
struct Rgbd {
    int64_t seq = 0;
    int64_t t_us = 0;  // exposure time, the hmd samples' clock
    int64_t width = 0, height = 0;
    std::array<float, 4> intrinsics{};  // fx, fy, cx, cy in pixels
    std::string rgb, depth;             // JPEG bytes, PNG bytes
    std::optional<std::array<float, 16>> cam_from_head;  // row-major 4x4 head device -> camera (m), this frame only
};

// Ask for the servable models; answered by `models`.
struct ListModels {};

// Liveness and round-trip time: `nonce` and `t_us` come back in `pong`.
struct Ping {
    std::optional<int64_t> nonce, t_us;
};

// Ask the server to measure the wearer (§4.1): hold `pose` ("tpose" or "stand") still for `seconds`; `clear`
// forgets the session's calibration.
struct Calibrate {
    std::string pose = "tpose";
    float seconds = 2.0f;
    bool clear = false;
};

constexpr size_t kBoneCount = 21;  // bone lengths: joints 1..21 (the §3 order), each from its parent
using BoneLengths = std::array<float, kBoneCount>;

// Ask for the wearer's body as the session knows it (§4.2); answered by `body`.
struct GetBody {};

// Serve a known wearer's body from the next hmd sample on (§4.2): the lengths a `body` gave (kept with the
// wearer's profile from an earlier session), or none with `clear` to estimate the body again.
struct SetBody {
    std::optional<BoneLengths> bone_lengths_m;
    bool clear = false;
};

struct Pose {
    int64_t seq = 0, t_us = 0;
    std::string model;
    std::array<float, 3> global_orient{};  // pelvis axis-angle (rad), SMPL canonical frame -> world
    std::array<float, 63> body_pose{};     // joints 1..21 local axis-angle (rad)
    std::array<float, 3> transl{};         // world position of the pelvis joint (m)
    std::array<float, 66> joints{};        // world positions of the 22 joints (m)
    std::map<std::string, int64_t> timing_us;
    std::optional<bool> camera;
    std::optional<int64_t> skipped;
    std::optional<std::array<bool, 2>> planted;  // left, right foot held planted on the floor (§planted-feet)
    std::optional<float> floor_y_m;              // world y (m) of the floor the served soles were held to
};

struct Error {
    std::string code, message;
    bool fatal = false;
    std::optional<std::string> ref_type;  // the type of the client message that caused it, when readable
};

// The wearer's body (§4.2), to every client after get_body and set_body. Keep a `measured` one with the wearer's
// profile and give it back (SetBody) first after the welcome of their next session.
struct Body {
    BoneLengths bone_lengths_m{};  // m
    bool given = false;            // a client gave it; otherwise the server's estimate
    bool measured = false;         // the camera measured the wearer's bones and they stood (or calibrated)
};

// The answer to hello.
struct Welcome {
    std::string session, role, server;  // server: "egoposevr/<version>"
    std::string model;                  // the session's active model
    std::vector<std::string> models;    // every servable model's name
    std::optional<std::string> provider;  // the execution provider of the active model ("none": no network)
};

// One servable model (§5 models). The digests say exactly which weights answered a session (§model-digests):
// log them with it. A model that is code (procedural) has neither; one that reads no camera has no encoder's.
// head_joint_m (§model-head-joint): where the model hangs the body's head joint, in the head device's frame (x
// right, y up, z back; m); none from a server older than the field (assume 0, -0.024, 0.083).
struct ModelInfo {
    std::string name;
    std::vector<std::string> inputs;  // a subset of "hmd", "rgb", "depth"
    std::string description;
    std::optional<std::string> sha256, encoder_sha256;  // 64 lowercase hex digits
    std::optional<std::array<float, 3>> head_joint_m;
};

// The models a session may select and the one it uses now: after the welcome, after list_models, and to every
// client of the session after any select_model.
struct Models {
    std::string active;
    std::vector<ModelInfo> models;
};

// Who is in a session (render clients): event "joined", "input_joined" or "input_left".
struct SessionStatus {
    std::string session, event, model;
    bool input = false;  // an input client is connected now
    int64_t renders = 0;
};

// Where a calibration stands (§4.1): status "started", "done", "failed" or "cleared".
struct Calibration {
    std::string status, pose, message;
    std::optional<float> head_height_m, arm_span_m;     // done: what was measured
    std::optional<std::array<float, 12>> corrections;  // done: head, left, right xyzw; R_device @ c from now on
};

struct Pong {
    std::optional<int64_t> nonce, t_us;  // echoed from the ping
    int64_t server_t_us = 0;             // the server's monotonic clock
};

class ProtocolError : public std::runtime_error {
   public:
    using std::runtime_error::runtime_error;
};

namespace detail {

inline void key(msgpack::packer<msgpack::sbuffer>& pk, const char* name) { pk.pack(std::string(name)); }

// A float32 (0xca) written by hand: msgpack-c 4's pack_float writes a whole-numbered float as an integer. The
// server accepts that too (§2), but float32 keeps a client's bytes equal to the server's and the golden fixtures.
inline void float32(msgpack::sbuffer& out, float value) {
    uint32_t bits;
    std::memcpy(&bits, &value, sizeof bits);
    const char bytes[5] = {char(0xca), char(bits >> 24), char(bits >> 16), char(bits >> 8), char(bits)};
    out.write(bytes, sizeof bytes);
}

// One message being written: the header (type, v), then each field's key and value in the table's order.
class Writer {
   public:
    Writer(size_t fields, const char* type) : packer_(&buffer_) {
        packer_.pack_map(fields + 2);
        field("type", std::string(type)).field("v", 1);
    }

    template <typename T>
    Writer& field(const char* name, const T& value) {
        key(packer_, name);
        packer_.pack(value);
        return *this;
    }

    Writer& float_field(const char* name, float value) {
        key(packer_, name);
        float32(buffer_, value);
        return *this;
    }

    template <size_t N>
    Writer& floats_field(const char* name, const std::array<float, N>& values) {
        key(packer_, name);
        packer_.pack_array(N);
        for (float v : values) float32(buffer_, v);
        return *this;
    }

    Writer& bin_field(const char* name, const std::string& bytes) {
        key(packer_, name);
        packer_.pack_bin(static_cast<uint32_t>(bytes.size()));
        packer_.pack_bin_body(bytes.data(), static_cast<uint32_t>(bytes.size()));
        return *this;
    }

    msgpack::sbuffer take() { return std::move(buffer_); }

   private:
    msgpack::sbuffer buffer_;
    msgpack::packer<msgpack::sbuffer> packer_;
};

inline const msgpack::object* find(const msgpack::object_map& map, const char* name) {
    for (uint32_t i = 0; i < map.size; ++i) {
        const msgpack::object& k = map.ptr[i].key;
        if (k.type == msgpack::type::STR && std::string(k.via.str.ptr, k.via.str.size) == name) return &map.ptr[i].val;
    }
    return nullptr;
}

// A field of a server message, read as one message is: `where` ("models.models[1]") names it in the error.
class Fields {
   public:
    Fields(const msgpack::object& object, std::string where) : where_(std::move(where)) {
        if (object.type != msgpack::type::MAP) throw ProtocolError(where_ + ": expected a map");
        map_ = &object.via.map;
    }

    const msgpack::object* optional(const char* name) const {
        const msgpack::object* value = find(*map_, name);
        return value == nullptr || value->type == msgpack::type::NIL ? nullptr : value;
    }

    const msgpack::object& required(const char* name) const {
        const msgpack::object* value = optional(name);
        if (value == nullptr) throw ProtocolError(path(name) + ": missing");
        return *value;
    }

    template <typename T>
    T get(const char* name) const {
        return as<T>(required(name), path(name));
    }

    template <typename T>
    std::optional<T> get_optional(const char* name) const {
        const msgpack::object* value = optional(name);
        if (value == nullptr) return std::nullopt;
        return as<T>(*value, path(name));
    }

    // A string field: msgpack str only (a bin where text belongs is refused, as the server's decoder does).
    std::string text(const char* name) const { return text_of(required(name), path(name)); }

    std::optional<std::string> optional_text(const char* name) const {
        const msgpack::object* value = optional(name);
        if (value == nullptr) return std::nullopt;
        return text_of(*value, path(name));
    }

    std::vector<std::string> texts(const char* name) const {
        const msgpack::object& value = array(name);
        std::vector<std::string> out;
        for (uint32_t i = 0; i < value.via.array.size; ++i)
            out.push_back(text_of(value.via.array.ptr[i], path(name) + "[" + std::to_string(i) + "]"));
        return out;
    }

    // An array of exactly N items of type T (`what` names them in the error: "numbers", "flags").
    template <typename T, size_t N>
    std::array<T, N> items(const char* name, const char* what) const {
        const msgpack::object& value = array(name);
        if (value.via.array.size != N)
            throw ProtocolError(path(name) + ": expected " + std::to_string(N) + " " + what + ", got " +
                                std::to_string(value.via.array.size));
        std::array<T, N> out{};
        for (size_t i = 0; i < N; ++i) out[i] = as<T>(value.via.array.ptr[i], path(name) + "[" + std::to_string(i) + "]");
        return out;
    }

    template <size_t N>
    std::array<float, N> floats(const char* name) const {
        return items<float, N>(name, "numbers");
    }

    template <size_t N>
    std::optional<std::array<float, N>> optional_floats(const char* name) const {
        if (optional(name) == nullptr) return std::nullopt;
        return floats<N>(name);
    }

    template <size_t N>
    std::optional<std::array<bool, N>> optional_flags(const char* name) const {
        if (optional(name) == nullptr) return std::nullopt;
        return items<bool, N>(name, "flags");
    }

    const msgpack::object& array(const char* name) const {
        const msgpack::object& value = required(name);
        if (value.type != msgpack::type::ARRAY) throw ProtocolError(path(name) + ": expected an array");
        return value;
    }

    std::string path(const std::string& name) const { return where_ + "." + name; }

   private:
    template <typename T>
    static T as(const msgpack::object& value, const std::string& where) {
        if constexpr (std::is_same_v<T, float>) {  // msgpack-c would read a bool as 0 or 1
            if (value.type == msgpack::type::BOOLEAN) throw ProtocolError(where + ": expected a number");
        }
        try {
            return value.as<T>();
        } catch (const msgpack::type_error&) {
            throw ProtocolError(where + ": wrong type");
        }
    }

    static std::string text_of(const msgpack::object& value, const std::string& where) {
        if (value.type != msgpack::type::STR) throw ProtocolError(where + ": expected a string");
        return {value.via.str.ptr, value.via.str.size};
    }

    const msgpack::object_map* map_ = nullptr;
    std::string where_;
};

}  // namespace detail

inline msgpack::sbuffer encode(const Hello& m) {
    detail::Writer w(2 + m.model.has_value() + m.token.has_value() + m.client.has_value(), "hello");
    w.field("role", m.role).field("session", m.session);
    for (auto [name, value] : {std::pair{"model", &m.model}, {"token", &m.token}, {"client", &m.client}})
        if (value->has_value()) w.field(name, **value);
    return w.take();
}

inline msgpack::sbuffer encode(const Hmd& m) {
    detail::Writer w(6, "hmd");
    w.field("seq", m.seq).field("t_us", m.t_us);
    w.floats_field("head", m.head).floats_field("left", m.left).floats_field("right", m.right);
    return w.field("valid", m.valid).take();
}

inline msgpack::sbuffer encode(const Rgbd& m) {
    detail::Writer w(7 + m.cam_from_head.has_value(), "rgbd");
    w.field("seq", m.seq).field("t_us", m.t_us).field("width", m.width).field("height", m.height);
    w.floats_field("intrinsics", m.intrinsics).bin_field("rgb", m.rgb).bin_field("depth", m.depth);
    if (m.cam_from_head) w.floats_field("cam_from_head", *m.cam_from_head);
    return w.take();
}

inline msgpack::sbuffer encode(const SelectModel& m) { return detail::Writer(1, "select_model").field("model", m.model).take(); }

inline msgpack::sbuffer encode(const Calibrate& m) {
    detail::Writer w(3, "calibrate");
    return w.field("pose", m.pose).float_field("seconds", m.seconds).field("clear", m.clear).take();
}

inline msgpack::sbuffer encode(const GetBody&) { return detail::Writer(0, "get_body").take(); }

// Throws std::invalid_argument for both lengths and clear, or neither (the server would refuse it).
inline msgpack::sbuffer encode(const SetBody& m) {
    if (m.bone_lengths_m.has_value() == m.clear)
        throw std::invalid_argument("set_body: give bone_lengths_m or clear, not both and not neither");
    detail::Writer w(m.clear ? 1 : 2, "set_body");
    if (m.bone_lengths_m) w.floats_field("bone_lengths_m", *m.bone_lengths_m);
    return w.field("clear", m.clear).take();
}

inline msgpack::sbuffer encode(const ListModels&) { return detail::Writer(0, "list_models").take(); }

inline msgpack::sbuffer encode(const Ping& m) {
    detail::Writer w(m.nonce.has_value() + m.t_us.has_value(), "ping");
    if (m.nonce) w.field("nonce", *m.nonce);
    if (m.t_us) w.field("t_us", *m.t_us);
    return w.take();
}

// The `type` of a server message; throws ProtocolError for bytes that are not one msgpack map with a type.
inline std::string message_type(const msgpack::object_handle& handle) {
    const msgpack::object& root = handle.get();
    if (root.type != msgpack::type::MAP) throw ProtocolError("not a msgpack map");
    const msgpack::object* type = detail::find(root.via.map, "type");
    if (type == nullptr || type->type != msgpack::type::STR) throw ProtocolError("type is missing or not a string");
    return type->as<std::string>();
}

// What a v1 server message can hold (models: 256 entries; texts: 1 KiB): a length past these is damage, refused
// before msgpack-c allocates for it.
inline msgpack::unpack_limit server_message_limits() {
    return msgpack::unpack_limit(/*array=*/1024, /*map=*/256, /*str=*/64 * 1024, /*bin=*/16 * 1024 * 1024,
                                 /*ext=*/0, /*depth=*/8);
}

inline msgpack::object_handle unpack(const char* data, size_t size) {
    try {
        size_t offset = 0;
        msgpack::object_handle handle =
            msgpack::unpack(data, size, offset, nullptr, nullptr, server_message_limits());
        if (offset != size) throw ProtocolError("trailing bytes after the message");
        return handle;
    } catch (const msgpack::unpack_error& exc) {
        throw ProtocolError(std::string("not msgpack: ") + exc.what());
    }
}

// Each read_* takes a message whose message_type the caller checked and throws ProtocolError, naming the field,
// for one that breaks §5's table. Fields the table does not list are ignored (§8: later servers may add some).

inline Pose read_pose(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "pose");
    Pose pose;
    pose.seq = f.get<int64_t>("seq");
    pose.t_us = f.get<int64_t>("t_us");
    pose.model = f.text("model");
    pose.global_orient = f.floats<3>("global_orient");
    pose.body_pose = f.floats<63>("body_pose");
    pose.transl = f.floats<3>("transl");
    pose.joints = f.floats<66>("joints");
    pose.timing_us = f.get<std::map<std::string, int64_t>>("timing_us");
    pose.camera = f.get_optional<bool>("camera");
    pose.skipped = f.get_optional<int64_t>("skipped");
    pose.planted = f.optional_flags<2>("planted");
    pose.floor_y_m = f.get_optional<float>("floor_y_m");
    return pose;
}

inline Error read_error(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "error");
    Error error{f.text("code"), f.text("message"), f.get<bool>("fatal"), std::nullopt};
    if (const msgpack::object* ref = f.optional("ref"); ref != nullptr && ref->type == msgpack::type::MAP)
        error.ref_type = detail::Fields(*ref, "error.ref").optional_text("type");
    return error;
}

inline Body read_body(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "body");
    return {f.floats<kBoneCount>("bone_lengths_m"), f.get<bool>("given"), f.get<bool>("measured")};
}

inline Welcome read_welcome(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "welcome");
    return {f.text("session"), f.text("role"), f.text("server"), f.text("model"), f.texts("models"),
            f.optional_text("provider")};
}

inline Models read_models(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "models");
    Models models{f.text("active"), {}};
    const msgpack::object& list = f.array("models");
    for (uint32_t i = 0; i < list.via.array.size; ++i) {
        const detail::Fields m(list.via.array.ptr[i], f.path("models") + "[" + std::to_string(i) + "]");
        models.models.push_back({m.text("name"), m.texts("inputs"), m.optional_text("description").value_or(""),
                                 m.optional_text("sha256"), m.optional_text("encoder_sha256"),
                                 m.optional_floats<3>("head_joint_m")});
    }
    return models;
}

inline SessionStatus read_session(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "session");
    return {f.text("session"), f.text("event"), f.text("model"), f.get<bool>("input"), f.get<int64_t>("renders")};
}

inline Calibration read_calibration(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "calibration");
    return {f.text("status"),
            f.text("pose"),
            f.optional_text("message").value_or(""),
            f.get_optional<float>("head_height_m"),
            f.get_optional<float>("arm_span_m"),
            f.optional_floats<12>("corrections")};
}

inline Pong read_pong(const msgpack::object_handle& handle) {
    const detail::Fields f(handle.get(), "pong");
    return {f.get_optional<int64_t>("nonce"), f.get_optional<int64_t>("t_us"), f.get<int64_t>("server_t_us")};
}

// ------------------------------------------------------------------------------ frames (PROTOCOL.md §3.2, §3.3)
struct Vec3 {
    double x, y, z;
};
struct Quat {
    double x, y, z, w;
};

// Protocol position (m) -> Unreal FVector (cm): 100 * (-pz, px, py).
inline Vec3 to_unreal_position(double px, double py, double pz) { return {-100 * pz, 100 * px, 100 * py}; }
// Protocol quaternion -> Unreal FQuat: (qz, -qx, -qy, qw).
inline Quat to_unreal_rotation(const Quat& q) { return {q.z, -q.x, -q.y, q.w}; }
// Unreal FVector (cm) -> protocol position (m): (y, z, -x) / 100.
inline Vec3 from_unreal_position(const Vec3& v) { return {v.y / 100, v.z / 100, -v.x / 100}; }
// Unreal FQuat -> protocol quaternion: (-y, -z, x, w).
inline Quat from_unreal_rotation(const Quat& q) { return {-q.y, -q.z, q.x, q.w}; }

inline Quat multiply(const Quat& a, const Quat& b) {
    return {a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y, a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
            a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w, a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z};
}

// The protocol's controller pose from an OpenXR grip pose in the protocol's frame (§3.3): a quarter turn about
// the grip's own Z, +90 degrees for the left hand, -90 for the right.
inline Pose7 controller_from_grip(const Vec3& p, const Quat& grip, bool left_hand) {
    const double half = std::sqrt(0.5);
    Quat q = multiply(grip, {0, 0, left_hand ? half : -half, half});
    return {float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z), float(q.w)};
}

// A device pose from Unreal's tracking-space position (cm) and rotation.
inline Pose7 pose_from_unreal(const Vec3& position_cm, const Quat& rotation) {
    Vec3 p = from_unreal_position(position_cm);
    Quat q = from_unreal_rotation(rotation);
    return {float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z), float(q.w)};
}

// ------------------------------------------------------------------------- planted feet (PROTOCOL.md §planted-feet)
// An avatar of other proportions that copies the served rotations moves its feet whenever its hips move over
// them, even while the server holds them planted. FootPins remembers where each planted foot landed, and reach()
// gives the two-bone IK turns (knee, then thigh) that put the foot back there as far as the leg reaches: the
// Unity package's FootPins, the same math. Positions and quaternions in any one frame (pin the avatar's joints
// in the protocol's frame, then convert them to Unreal's with to_unreal_position and to_unreal_rotation).

// The vector v turned by the unit quaternion q (v' = q v q*).
inline Vec3 rotate(const Quat& q, const Vec3& v) {
    const Vec3 t{2 * (q.y * v.z - q.z * v.y), 2 * (q.z * v.x - q.x * v.z), 2 * (q.x * v.y - q.y * v.x)};
    return {v.x + q.w * t.x + q.y * t.z - q.z * t.y, v.y + q.w * t.y + q.z * t.x - q.x * t.z,
            v.z + q.w * t.z + q.x * t.y - q.y * t.x};
}

namespace detail {
constexpr double kPi = 3.14159265358979323846;
inline Vec3 add(const Vec3& a, const Vec3& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline Vec3 sub(const Vec3& a, const Vec3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 scaled(const Vec3& a, double s) { return {a.x * s, a.y * s, a.z * s}; }
inline double dot(const Vec3& a, const Vec3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double norm(const Vec3& a) { return std::sqrt(dot(a, a)); }
inline Vec3 unit(const Vec3& a) { return scaled(a, 1 / norm(a)); }
inline Vec3 cross(const Vec3& a, const Vec3& b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline Vec3 across(const Vec3& v, const Vec3& unit_line) { return sub(v, scaled(unit_line, dot(v, unit_line))); }
inline Quat axis_angle(const Vec3& unit_axis, double angle) {
    const double s = std::sin(angle / 2);
    return {unit_axis.x * s, unit_axis.y * s, unit_axis.z * s, std::cos(angle / 2)};
}
// The shortest turn from unit a to unit b (half a turn about any perpendicular where they are opposite).
inline Quat from_to(const Vec3& a, const Vec3& b) {
    const double w = 1 + dot(a, b);
    if (w < 1e-9) return axis_angle(unit(std::abs(a.x) < 0.9 ? cross(a, {1, 0, 0}) : cross(a, {0, 1, 0})), kPi);
    const Vec3 c = cross(a, b);
    const double n = std::sqrt(dot(c, c) + w * w);
    return {c.x / n, c.y / n, c.z / n, w / n};
}
}  // namespace detail

class FootPins {
public:
    static constexpr double kSlack = 1.2;          // a pin farther than this many leg lengths from its hip is dropped
    static constexpr int64_t kGapUs = 500000;      // after a pause this long between poses (µs) feet land anew
    static constexpr double kFrontPullM = 0.1;     // the knee's way off its hip-to-ankle line gets this much front

    // Where foot `side` (0 left, 1 right) should be for the pose at t_us: nothing while it is not planted, or in
    // the pose where it lands (it stays where the pose put it, `foot`, which becomes its pin); afterwards, that
    // pin. Call once per side and pose, the left first.
    std::optional<Vec3> target(int side, bool planted, int64_t t_us, const Vec3& hip, const Vec3& foot,
                               double leg_length_m) {
        if (side == 0) {
            if (last_t_us_ >= 0 && (t_us < last_t_us_ || t_us - last_t_us_ > kGapUs)) pins_[0] = pins_[1] = {};
            last_t_us_ = t_us;
        }
        std::optional<Vec3>& pin = pins_[side & 1];
        if (!planted) {
            pin.reset();
            return {};
        }
        if (!pin || detail::norm(detail::sub(*pin, hip)) > kSlack * leg_length_m) {
            pin = foot;
            return {};
        }
        return pin;
    }

    struct Turns {
        Quat knee;   // turns the shin about the knee: new world rotation = knee * old
        Quat thigh;  // then swings thigh and shin about the hip: new world rotation = thigh * (after the knee's)
    };

    // Two-bone IK: the world turns that bring the foot from `ankle` to `target` as far as the thigh and shin
    // reach. The knee bends the way it sits off the hip-to-ankle line, pulled towards `forward` (the body's
    // front), so a straight leg, or a rest knee that sits off the line sideways, bends forward and not out.
    static Turns reach(const Vec3& hip, const Vec3& knee, const Vec3& ankle, const Vec3& target, const Vec3& forward) {
        using namespace detail;
        const Vec3 to_hip = sub(hip, knee), to_ankle = sub(ankle, knee);
        const double thigh = norm(to_hip), shin = norm(to_ankle);
        const double span =
            std::max(std::abs(thigh - shin) + 1e-4, std::min(thigh + shin - 1e-4, norm(sub(target, hip))));
        const Vec3 line = unit(sub(ankle, hip));
        const Vec3 way = add(across(sub(knee, hip), line), scaled(across(unit(forward), line), kFrontPullM));
        const double cosine = (thigh * thigh + shin * shin - span * span) / (2 * thigh * shin);
        const double wanted = std::acos(std::max(-1.0, std::min(1.0, cosine)));
        // the shin's new way: the thigh's (knee to hip) turned by the knee angle wanted, in the bend plane
        const Vec3 shin_way = rotate(axis_angle(unit(cross(way, to_hip)), wanted), unit(to_hip));
        const Quat knee_turn = from_to(unit(to_ankle), shin_way);
        const Vec3 reached = add(sub(knee, hip), rotate(knee_turn, to_ankle));  // hip to the turned ankle
        return {knee_turn, from_to(unit(reached), unit(sub(target, hip)))};
    }

private:
    std::array<std::optional<Vec3>, 2> pins_{};
    int64_t last_t_us_ = -1;
};

}  // namespace egopose
