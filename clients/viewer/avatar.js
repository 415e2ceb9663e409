// A skinned humanoid avatar (VRM 0.x or 1.0, through three-vrm) driven by a pose's SMPL rotations.
//
// three-vrm's "normalized" humanoid gives every bone a rest rotation of identity in a T-pose facing +Z (VRM 1.0;
// VRM 0.x rests facing -Z), which is SMPL's rest pose. So a bone's normalized local rotation is the SMPL world
// rotation of its nearest present ancestor, inverted, times its own: missing optional bones (upperChest, toes,
// shoulders) are skipped without bending the chain. The hips go to `transl`, their height scaled by the avatar's
// leg length over the served one so that feet of any avatar meet the floor. World: right-handed, y up, metres.
// A foot the server holds planted (`pose.planted`, PROTOCOL.md §planted-feet) is pinned where the avatar's foot
// stood when it landed, by two-bone IK on the thigh and shin: the avatar's proportions differ from the served
// body's, so copied rotations alone would slide its feet whenever the hips move over them.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VRMLoaderPlugin } from "./vendor/three-vrm/three-vrm.module.min.js";

export const PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19];
// VRM humanoid bone of each SMPL joint (PROTOCOL.md §3 order).
export const VRM_BONES = [
  "hips", "leftUpperLeg", "rightUpperLeg", "spine", "leftLowerLeg", "rightLowerLeg", "chest", "leftFoot",
  "rightFoot", "upperChest", "leftToes", "rightToes", "neck", "leftShoulder", "rightShoulder", "head",
  "leftUpperArm", "rightUpperArm", "leftLowerArm", "rightLowerArm", "leftHand", "rightHand",
];
const YAW_180 = new THREE.Quaternion(0, 1, 0, 0);
const LEGS = [["leftUpperLeg", "leftLowerLeg", "leftFoot"], ["rightUpperLeg", "rightLowerLeg", "rightFoot"]];
const PIN_SLACK = 1.2; // a pin farther than this many leg lengths from its hip is dropped (a recentred space)
const PIN_GAP_US = 500000; // pins are dropped after a pause this long between shown poses
const FRONT_PULL_M = 0.1; // the knee's way off the hip-to-ankle line gets this much of the body's front added

function axisAngle(x, y, z) {
  const angle = Math.hypot(x, y, z);
  if (angle < 1e-9) return new THREE.Quaternion();
  return new THREE.Quaternion().setFromAxisAngle(new THREE.Vector3(x / angle, y / angle, z / angle), angle);
}

/** World rotations of the 22 SMPL joints from global_orient [3] and body_pose [63]. */
export function globalRotations(pose) {
  const rot = [axisAngle(...pose.global_orient)];
  for (let j = 1; j < 22; j++) {
    rot.push(rot[PARENTS[j]].clone().multiply(axisAngle(...pose.body_pose.slice(3 * (j - 1), 3 * j))));
  }
  return rot;
}

function legLength(a, b, c) { return a.distanceTo(b) + b.distanceTo(c); }

/** Turn `node` by the world rotation `turn` (its children go with it); world matrices kept current. */
function turnInWorld(node, turn) {
  const parent = node.parent.getWorldQuaternion(new THREE.Quaternion());
  const world = turn.clone().multiply(node.getWorldQuaternion(new THREE.Quaternion()));
  node.quaternion.copy(parent.invert().multiply(world));
  node.updateMatrixWorld(true);
}

/**
 * Two-bone IK: bend the knee (`lower`) so that hip to foot spans the hip's distance to `target` (as far as the
 * bones reach), then swing the thigh (`upper`) to point the chain at it. The knee goes the way it sits off the
 * hip-to-ankle line, pulled towards `forward` (the body's front); the foot keeps its world rotation.
 */
function reach(upper, lower, foot, target, forward) {
  const at = (node) => node.getWorldPosition(new THREE.Vector3());
  const footTurn = foot.getWorldQuaternion(new THREE.Quaternion());
  const [hip, knee, ankle] = [at(upper), at(lower), at(foot)];
  const thigh = hip.distanceTo(knee), shin = knee.distanceTo(ankle);
  const span = THREE.MathUtils.clamp(hip.distanceTo(target), Math.abs(thigh - shin) + 1e-4, thigh + shin - 1e-4);
  const toHip = hip.clone().sub(knee), toAnkle = ankle.clone().sub(knee);
  // The way the knee goes: where it is off the hip-to-ankle line, pulled to the body's front (a leg about straight,
  // or one whose rest knee sits off the line sideways, bends forward, not out)
  const line = ankle.clone().sub(hip).normalize();
  const off = knee.clone().sub(hip).projectOnPlane(line);
  const way = off.add(forward.clone().normalize().projectOnPlane(line).multiplyScalar(FRONT_PULL_M));
  const axis = way.cross(toHip);
  const wanted = Math.acos(THREE.MathUtils.clamp((thigh * thigh + shin * shin - span * span) / (2 * thigh * shin), -1, 1));
  // the shin's new way: the thigh's (knee to hip) turned by the knee angle wanted, in the bend plane
  const shinWay = toHip.clone().normalize().applyQuaternion(new THREE.Quaternion().setFromAxisAngle(axis.normalize(), wanted));
  turnInWorld(lower, new THREE.Quaternion().setFromUnitVectors(toAnkle.clone().normalize(), shinWay));
  const reached = at(foot).sub(hip).normalize();
  turnInWorld(upper, new THREE.Quaternion().setFromUnitVectors(reached, target.clone().sub(hip).normalize()));
  foot.quaternion.copy(foot.parent.getWorldQuaternion(new THREE.Quaternion()).invert().multiply(footTurn));
  foot.updateMatrixWorld(true);
}

/** The 22 joints of a flat [66] array (`pose.joints`, `pose.truth`) as vectors. */
export function jointsOf(flat) {
  const out = [];
  for (let j = 0; j < 22; j++) out.push(new THREE.Vector3(flat[3 * j], flat[3 * j + 1], flat[3 * j + 2]));
  return out;
}

/** Parse .vrm bytes into a three-vrm VRM. */
export async function parseVrm(bytes) {
  const loader = new GLTFLoader();
  loader.register((parser) => new VRMLoaderPlugin(parser));
  const gltf = await loader.parseAsync(bytes, "");
  const vrm = gltf.userData.vrm;
  if (!vrm || !vrm.humanoid) throw new Error("not a VRM humanoid (no VRM extension)");
  return vrm;
}

/** A loaded VRM and how to pose it. */
export class Avatar {
  constructor(vrm, name) {
    this.vrm = vrm;
    this.name = name;
    this.vrm0 = vrm.meta?.metaVersion === "0";
    const humanoid = vrm.humanoid;
    this.nodes = VRM_BONES.map((bone) => humanoid.getNormalizedBoneNode(bone));
    // Each joint's nearest ancestor that the avatar has (-1: none above).
    this.present = PARENTS.map((p) => { while (p >= 0 && !this.nodes[p]) p = PARENTS[p]; return p; });
    vrm.scene.updateMatrixWorld(true);
    const at = (bone) => humanoid.getRawBoneNode(bone).getWorldPosition(new THREE.Vector3());
    this.legM = legLength(at("leftUpperLeg"), at("leftLowerLeg"), at("leftFoot"));
    this.legNodes = LEGS.map((chain) => chain.map((bone) => humanoid.getNormalizedBoneNode(bone)));
    this.pins = [null, null]; // each planted foot's spot in the world, where the avatar's foot stood at landing
    this.shownUs = undefined; // t_us of the last pose shown
    vrm.scene.traverse((o) => { o.frustumCulled = false; }); // skinned bounds lag behind the pose
  }

  /** Put the avatar in `pose` (a protocol pose: global_orient, body_pose, transl, joints). */
  show(pose) {
    const rot = globalRotations(pose);
    for (let j = 0; j < 22; j++) {
      const node = this.nodes[j];
      if (!node) continue;
      const p = this.present[j];
      const local = p >= 0 ? rot[p].clone().invert().multiply(rot[j]) : rot[j].clone();
      if (this.vrm0) { // VRM 0.x rests facing -Z: turn the root, and every local rotation into the turned frame
        if (p < 0) local.multiply(YAW_180);
        else local.premultiply(YAW_180).multiply(YAW_180);
      }
      node.quaternion.copy(local);
    }
    const joints = jointsOf(pose.joints);
    const served = legLength(joints[1], joints[4], joints[7]);
    const scale = served > 0.1 ? this.legM / served : 1;
    this.nodes[0].position.set(pose.transl[0], pose.transl[1] * scale, pose.transl[2]);
    this.vrm.scene.updateMatrixWorld(true);
    const gap = pose.t_us - this.shownUs; // a pose after a pause (or from another stream) lands anew
    if (gap < 0 || gap > PIN_GAP_US) this.pins = [null, null];
    this.shownUs = pose.t_us;
    this.pinFeet(pose.planted);
    this.vrm.update(0);
    this.vrm.scene.updateMatrixWorld(true);
  }

  /** Keep each planted foot on its spot (`planted`: the pose's [left, right], or undefined: none planted). */
  pinFeet(planted) {
    const hips = this.legNodes.map(([upper]) => upper?.getWorldPosition(new THREE.Vector3()));
    const forward = hips[0] && hips[1]
      ? hips[0].clone().sub(hips[1]).cross(new THREE.Vector3(0, 1, 0))
      : new THREE.Vector3(0, 0, 1);
    this.legNodes.forEach(([upper, lower, foot], k) => {
      if (!upper || !lower || !foot || !(planted && planted[k])) { this.pins[k] = null; return; }
      const hip = hips[k];
      const now = foot.getWorldPosition(new THREE.Vector3());
      if (!this.pins[k] || this.pins[k].distanceTo(hip) > PIN_SLACK * this.legM) { this.pins[k] = now; return; }
      reach(upper, lower, foot, this.pins[k], forward);
    });
  }

  /** {bone: [x, y, z]} world positions of the avatar's own (raw) bones: what the skin follows. */
  bonePositions() {
    const out = {};
    for (const bone of VRM_BONES) {
      const node = this.vrm.humanoid.getRawBoneNode(bone);
      if (node) out[bone] = node.getWorldPosition(new THREE.Vector3()).toArray();
    }
    return out;
  }
}
