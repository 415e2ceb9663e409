// EgoPose protocol v1 for C++ (PROTOCOL.md): the messages an Unreal (or any C++) headset client sends and the
// pose it reads, encoded with msgpack-c (msgpack-cxx, header-only), and the frame conversions of §3.2.
//
// Plain C++17 and msgpack-cxx, no Unreal types: tests/clients/test_unreal_core.py compiles it with g++ and checks
// it against the golden fixtures. EgoPoseComponent.h/.cpp is the Unreal side that uses it.
//
// Frames: the protocol's world is right-handed, +Y up, -Z forward, metres; quaternions (x, y, z, w). Unreal's is
// left-handed, +Z up, +X forward, +Y right, centimetres.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>

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

inline const msgpack::object& field(const msgpack::object_map& map, const char* name) {
    const msgpack::object* value = find(map, name);
    if (value == nullptr || value->type == msgpack::type::NIL) throw ProtocolError(std::string("missing ") + name);
    return *value;
}

template <size_t N>
std::array<float, N> read_floats(const msgpack::object_map& map, const char* name) {
    const msgpack::object& value = field(map, name);
    if (value.type != msgpack::type::ARRAY || value.via.array.size != N)
        throw ProtocolError(std::string(name) + ": expected " + std::to_string(N) + " numbers");
    std::array<float, N> out{};
    for (size_t i = 0; i < N; ++i) out[i] = value.via.array.ptr[i].as<float>();
    return out;
}

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

// The `type` of a server message; throws ProtocolError for bytes that are not one msgpack map with a type.
inline std::string message_type(const msgpack::object_handle& handle) {
    const msgpack::object& root = handle.get();
    if (root.type != msgpack::type::MAP) throw ProtocolError("not a msgpack map");
    const msgpack::object& type = detail::field(root.via.map, "type");
    if (type.type != msgpack::type::STR) throw ProtocolError("type is not a string");
    return type.as<std::string>();
}

inline msgpack::object_handle unpack(const char* data, size_t size) {
    try {
        size_t offset = 0;
        msgpack::object_handle handle = msgpack::unpack(data, size, offset);
        if (offset != size) throw ProtocolError("trailing bytes after the message");
        return handle;
    } catch (const msgpack::unpack_error& exc) {
        throw ProtocolError(std::string("not msgpack: ") + exc.what());
    }
}

// A `pose` message's fields (the caller checked message_type == "pose").
inline Pose read_pose(const msgpack::object_handle& handle) {
    const msgpack::object_map& map = handle.get().via.map;
    Pose pose;
    pose.seq = detail::field(map, "seq").as<int64_t>();
    pose.t_us = detail::field(map, "t_us").as<int64_t>();
    pose.model = detail::field(map, "model").as<std::string>();
    pose.global_orient = detail::read_floats<3>(map, "global_orient");
    pose.body_pose = detail::read_floats<63>(map, "body_pose");
    pose.transl = detail::read_floats<3>(map, "transl");
    pose.joints = detail::read_floats<66>(map, "joints");
    pose.timing_us = detail::field(map, "timing_us").as<std::map<std::string, int64_t>>();
    if (auto camera = detail::find(map, "camera"); camera && camera->type != msgpack::type::NIL)
        pose.camera = camera->as<bool>();
    if (auto skipped = detail::find(map, "skipped"); skipped && skipped->type != msgpack::type::NIL)
        pose.skipped = skipped->as<int64_t>();
    return pose;
}

inline Error read_error(const msgpack::object_handle& handle) {
    const msgpack::object_map& map = handle.get().via.map;
    Error error{detail::field(map, "code").as<std::string>(), detail::field(map, "message").as<std::string>(),
                detail::field(map, "fatal").as<bool>(), std::nullopt};
    if (auto ref = detail::find(map, "ref"); ref && ref->type == msgpack::type::MAP)
        error.ref_type = detail::field(ref->via.map, "type").as<std::string>();
    return error;
}

// A `body` message's fields (the caller checked message_type == "body").
inline Body read_body(const msgpack::object_handle& handle) {
    const msgpack::object_map& map = handle.get().via.map;
    return {detail::read_floats<kBoneCount>(map, "bone_lengths_m"), detail::field(map, "given").as<bool>(),
            detail::field(map, "measured").as<bool>()};
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

}  // namespace egopose
