// The 3D twin: the robot built from its URDF and meshes (served by the robot-types API),
// drawn twice: solid orange at the commanded (virtual) pose, and as a cyan ghost (a faint skin
// and its outline) at the measured (real) pose. The two often stand in one place: the ghost's
// outline is drawn over the solid arm there, so both still show.

import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";
import { STLLoader } from "three/examples/jsm/loaders/STLLoader.js";
import { call, fetchBytes, fetchText } from "./api.js";

/** The two arms' colours; the page's legend takes them from here. */
export const COMMANDED_COLOR = 0xe8a33d;
export const MEASURED_COLOR = 0x3dd6e8;

/** A colour of this module as CSS, with an optional opacity. */
export function cssColor(color, alpha = 1) {
  return `rgba(${color >> 16}, ${(color >> 8) & 255}, ${color & 255}, ${alpha})`;
}

// Edges between faces meeting at more than this (degrees) outline the ghost: its shape
// without the mesh's every triangle.
const OUTLINE_ANGLE = 35;

/** URDF `xyz` / `rpy` attributes as three numbers (missing means zeros). */
function triple(text) {
  const values = (text || "").trim().split(/\s+/).filter(Boolean).map(Number);
  return values.length === 3 && values.every(Number.isFinite) ? values : [0, 0, 0];
}

/** Place `object` at a URDF <origin>: translation, then fixed-axis roll, pitch, yaw. */
function applyOrigin(object, origin) {
  if (!origin) return;
  object.position.fromArray(triple(origin.getAttribute("xyz")));
  const [roll, pitch, yaw] = triple(origin.getAttribute("rpy"));
  // URDF's fixed-axis R = Rz(yaw) Ry(pitch) Rx(roll) is three.js's intrinsic "ZYX" order.
  object.rotation.set(roll, pitch, yaw, "ZYX");
}

/** The parsed URDF: links with their visuals, joints with frames and axes. */
export function parseUrdf(text) {
  const xml = new DOMParser().parseFromString(text, "application/xml");
  if (xml.querySelector("parsererror")) throw new Error("The URDF is not valid XML.");
  const robot = xml.documentElement;
  const links = [...robot.children].filter((e) => e.tagName === "link");
  const joints = [...robot.children]
    .filter((e) => e.tagName === "joint")
    .map((e) => ({
      name: e.getAttribute("name"),
      type: e.getAttribute("type"),
      parent: e.querySelector("parent").getAttribute("link"),
      child: e.querySelector("child").getAttribute("link"),
      origin: e.querySelector("origin"),
      axis: new THREE.Vector3(...triple(e.querySelector("axis")?.getAttribute("xyz") || "1 0 0")),
    }));
  return { links, joints };
}

/** The distance from `object`'s origin to the furthest vertex of its meshes (matrices
 * up to date). Vertices, not bounding boxes: a box's corners lie well beyond a slanted part. */
function furthestVertex(object) {
  const inverse = object.matrixWorld.clone().invert();
  const point = new THREE.Vector3();
  let furthest = 0;
  object.traverse((part) => {
    if (!part.isMesh) return;
    const toObject = inverse.clone().multiply(part.matrixWorld);
    const positions = part.geometry.attributes.position;
    for (let i = 0; i < positions.count; i++) {
      point.fromBufferAttribute(positions, i).applyMatrix4(toObject);
      furthest = Math.max(furthest, point.length());
    }
  });
  return furthest;
}

/** Points on the surface of what an arm of `reach` can reach (three.js axes, y up, its base
 * at the origin): the sphere of its reach, cut at the floor (`floor` height, -reach for none),
 * with the circle where the floor cuts it. */
function reachable(reach, floor) {
  const points = [];
  const count = 400;
  for (let i = 0; i < count; i++) {
    // spread evenly over the sphere (a Fibonacci spiral)
    const y = 1 - (2 * (i + 0.5)) / count;
    const around = Math.sqrt(1 - y * y);
    const angle = i * Math.PI * (3 - Math.sqrt(5));
    const point = new THREE.Vector3(around * Math.cos(angle), y, around * Math.sin(angle));
    if (point.y * reach >= floor) points.push(point.multiplyScalar(reach));
  }
  const rim = Math.sqrt(Math.max(reach * reach - floor * floor, 0));
  for (let i = 0; i < 48; i++) {
    const angle = (i / 48) * 2 * Math.PI;
    points.push(new THREE.Vector3(rim * Math.cos(angle), floor, rim * Math.sin(angle)));
  }
  return points;
}

/** One drawable copy of the robot: its root object and a setter for joint angles (radians).
 * With `outline` (a line material and a cache of edge geometries) each part is outlined too. */
class RobotCopy {
  constructor(urdf, geometries, material, outline = null) {
    this.root = new THREE.Group();
    this.motions = new Map();
    this.linkObjects = new Map();
    for (const link of urdf.links) {
      const object = new THREE.Group();
      object.name = link.getAttribute("name");
      for (const visual of link.querySelectorAll("visual")) {
        const mesh = visual.querySelector("geometry > mesh");
        const geometry = mesh && geometries.get(mesh.getAttribute("filename"));
        if (!geometry) continue;
        const part = new THREE.Mesh(geometry, material);
        if (outline) {
          let edges = outline.edges.get(geometry);
          if (!edges) {
            edges = new THREE.EdgesGeometry(geometry, OUTLINE_ANGLE);
            outline.edges.set(geometry, edges);
          }
          part.add(new THREE.LineSegments(edges, outline.material));
        }
        applyOrigin(part, visual.querySelector("origin"));
        const scale = mesh.getAttribute("scale");
        if (scale) part.scale.fromArray(triple(scale));
        object.add(part);
      }
      this.linkObjects.set(object.name, object);
    }
    // How far each link's parts reach from its frame's origin (its own parts only: taken
    // before the child links hang on it), for the arm's reach below.
    const partsReach = new Map();
    for (const [name, object] of this.linkObjects) {
      object.updateMatrixWorld(true);
      partsReach.set(name, furthestVertex(object));
    }
    const children = new Set(urdf.joints.map((j) => j.child));
    for (const joint of urdf.joints) {
      const frame = new THREE.Group();
      applyOrigin(frame, joint.origin);
      const motion = new THREE.Group();
      frame.add(motion);
      motion.add(this.linkObjects.get(joint.child));
      this.linkObjects.get(joint.parent).add(frame);
      this.motions.set(joint.name, { motion, joint });
    }
    for (const [name, object] of this.linkObjects) {
      if (!children.has(name)) this.root.add(object);
    }
    // The arm's reach: no part of it, in any pose, is further than this from its base. Each
    // link's frame is at most the sum of the joint offsets above it away (a prismatic joint
    // would add its travel; these arms have none), and its parts reach further by their own.
    const frameReach = (name) => {
      const joint = urdf.joints.find((j) => j.child === name);
      if (!joint) return 0;
      const offset = new THREE.Vector3(...triple(joint.origin?.getAttribute("xyz"))).length();
      return frameReach(joint.parent) + offset;
    };
    this.reach = Math.max(
      ...[...this.linkObjects.keys()].map((name) => frameReach(name) + partsReach.get(name)),
    );
    // The deepest link: its world position tells where the arm's tip is.
    this.tip = this.linkObjects.get(urdf.joints.length ? urdf.joints.at(-1).child : urdf.links[0]);
  }

  /** Set one joint: radians for revolute joints, metres for prismatic ones. */
  setJoint(name, value) {
    const entry = this.motions.get(name);
    if (!entry || !Number.isFinite(value)) return;
    if (entry.joint.type === "prismatic") {
      entry.motion.position.copy(entry.joint.axis).multiplyScalar(value);
    } else if (entry.joint.type !== "fixed") {
      entry.motion.quaternion.setFromAxisAngle(entry.joint.axis, value);
    }
  }

  /** Where the tip link is in the world (the scene's frame), rounded to 0.1 mm. */
  tipPosition() {
    this.root.updateMatrixWorld(true);
    const at = this.tip.getWorldPosition(new THREE.Vector3());
    return [at.x, at.y, at.z].map((v) => Math.round(v * 10000) / 10000);
  }
}

/** A robot type drawn in `container`, with `show(joints)` to follow the wire's joint states. */
export class Twin {
  static async create(container, robotType) {
    const type = await call("GET", `/api/robot-types/${encodeURIComponent(robotType)}`);
    const urdfText = await fetchText(type.urdf);
    const urdf = parseUrdf(urdfText);
    const geometries = new Map();
    const loader = new STLLoader();
    const names = new Set();
    for (const mesh of urdfText.matchAll(/<mesh[^>]*filename="([^"]+)"/g)) names.add(mesh[1]);
    await Promise.all(
      [...names].map(async (name) => {
        try {
          const geometry = loader.parse(await fetchBytes(type.files + name));
          geometry.computeVertexNormals();
          geometries.set(name, geometry);
        } catch {
          // A missing mesh leaves its part out; the pose is still computed and shown.
        }
      }),
    );
    return new Twin(container, type, urdf, geometries);
  }

  constructor(container, type, urdf, geometries) {
    this.container = container;
    this.type = type;
    this.commanded = new RobotCopy(
      urdf,
      geometries,
      new THREE.MeshStandardMaterial({
        color: COMMANDED_COLOR,
        metalness: 0.1,
        roughness: 0.6,
        // pushed back a little in depth: where the arms coincide, the ghost's lines win
        polygonOffset: true,
        polygonOffsetFactor: 1,
        polygonOffsetUnits: 1,
      }),
    );
    this.measured = new RobotCopy(
      urdf,
      geometries,
      new THREE.MeshBasicMaterial({
        color: MEASURED_COLOR,
        transparent: true,
        opacity: 0.14,
        depthWrite: false,
      }),
      { material: new THREE.LineBasicMaterial({ color: MEASURED_COLOR }), edges: new Map() },
    );
    this.measured.root.visible = false; // until a slave measures something
    this.measuring = true; // whether a slave is attached (the robot keeps its last real values)
    this.hasReal = false;
    this.scene = new THREE.Scene();
    const world = new THREE.Group();
    world.rotation.x = -Math.PI / 2; // URDF is z-up, three.js is y-up
    world.add(this.commanded.root, this.measured.root);
    this.workspace = new THREE.Group(); // the collision guard's floor and keep-out boxes
    world.add(this.workspace);
    this.scene.add(world);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x404050, 2.2));
    const sun = new THREE.DirectionalLight(0xffffff, 1.5);
    sun.position.set(0.5, 1, 0.7);
    this.scene.add(sun);
    this.scene.add(new THREE.GridHelper(0.6, 12, 0x888888, 0x444444));
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 10);
    this.camera.position.set(0.35, 0.35, 0.45);
    try {
      this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
      this.renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
      container.append(this.renderer.domElement);
      this.controls = new OrbitControls(this.camera, this.renderer.domElement);
      this.controls.addEventListener("change", () => this.render());
      // Once a hand turns or zooms the view, the view is the hand's: it is never re-aimed.
      this.controls.addEventListener("start", () => (this.userAimed = true));
      new ResizeObserver(() => this.resize()).observe(container);
      this.resize();
    } catch {
      this.renderer = null; // no WebGL here: the pose is still tracked, just not drawn
      container.textContent = "3D view unavailable (this browser has no WebGL).";
    }
    this.show([]);
  }

  resize() {
    const width = this.container.clientWidth || 300;
    const height = this.container.clientHeight || 240;
    this.renderer.setSize(width, height);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    if (!this.userAimed) this.frame(); // a narrower view needs a longer step back
    this.render();
  }

  /** Whether a slave is attached to measure: without one there is no ghost (the robot's real
   * values are then only the last ones measured). */
  setMeasuring(measuring) {
    this.measuring = measuring;
    this.showGhost();
  }

  showGhost() {
    const shown = this.measuring && this.hasReal;
    this.container.dataset.ghost = shown ? "shown" : "hidden";
    if (this.measured.root.visible === shown) return;
    this.measured.root.visible = shown;
    this.render();
  }

  /** Follow a `joint_states` message: virtual values pose the solid arm, real ones the ghost.
   * With no real values (no slave measures) there is no ghost: it would stand where nothing is. */
  show(states) {
    const byName = new Map(this.type.joints.map((j) => [j.name, j]));
    let measured = false;
    for (const state of states) {
      const spec = byName.get(state.name);
      if (!spec) continue;
      const toUrdf = (value) => spec.neutral + value * (spec.radians_per_unit ?? Math.PI / 180);
      this.commanded.setJoint(state.name, toUrdf(state.virtual_value));
      if (state.real_value !== null && state.real_value !== undefined) {
        this.measured.setJoint(state.name, toUrdf(state.real_value));
        measured = true;
      }
    }
    this.hasReal = measured;
    this.showGhost();
    // The tips' positions, for people reading the page and for the browser tests.
    this.container.dataset.tip = this.commanded.tipPosition().join(",");
    this.container.dataset.ghostTip = this.measured.tipPosition().join(",");
    this.container.dataset.inView = this.armInView();
    this.render();
  }

  /** Draw a workspace (`GET /api/robots/{id}/workspace`): the floor as a translucent plate,
   * each keep-out box as a red translucent box with its edges. Units are metres, z up. */
  showWorkspace(workspace) {
    this.workspace.clear();
    this.floor = workspace.floor; // the arm reaches nothing below it: the view need not either
    if (!this.userAimed) this.frame();
    if (workspace.floor !== null && workspace.floor !== undefined) {
      const plate = new THREE.Mesh(
        new THREE.PlaneGeometry(0.8, 0.8),
        new THREE.MeshBasicMaterial({
          color: 0x6b7b8c,
          transparent: true,
          opacity: 0.25,
          side: THREE.DoubleSide,
          depthWrite: false,
        }),
      );
      plate.position.z = workspace.floor - 0.0005; // just under the base, no z-fighting
      plate.name = "floor";
      this.workspace.add(plate);
    }
    for (const box of workspace.keep_out || []) {
      const size = box.max.map((high, i) => high - box.min[i]);
      const geometry = new THREE.BoxGeometry(...size);
      const solid = new THREE.Mesh(
        geometry,
        new THREE.MeshBasicMaterial({
          color: 0xd9534f,
          transparent: true,
          opacity: 0.2,
          depthWrite: false,
        }),
      );
      const edges = new THREE.EdgesGeometry(geometry);
      solid.add(new THREE.LineSegments(edges, new THREE.LineBasicMaterial({ color: 0xd9534f })));
      solid.position.set(...box.max.map((high, i) => (high + box.min[i]) / 2));
      solid.name = box.name;
      this.workspace.add(solid);
    }
    this.container.dataset.workspace = this.workspace.children.map((c) => c.name).join(",");
    this.render();
  }

  /** Show what a refused command would have hit: those links (and the floor or box) in red for
   * a few seconds. */
  showHit(names) {
    const red = new THREE.MeshStandardMaterial({ color: 0xd9534f, emissive: 0x661111 });
    const restore = [];
    for (const name of names) {
      const link = this.commanded.linkObjects.get(name);
      const parts = link ? link.children.filter((c) => c.isMesh) : [];
      const obstacle = this.workspace.children.find((c) => c.name === name);
      for (const part of obstacle ? [...parts, obstacle] : parts) {
        restore.push([part, part.material]);
        part.material = red;
      }
    }
    this.container.dataset.hit = names.join(",");
    this.render();
    clearTimeout(this.hitTimer);
    this.hitTimer = setTimeout(() => {
      for (const [part, material] of restore) part.material = material;
      this.render();
    }, 3000);
  }

  /** Aim the camera at where the arm can reach, from the front-right and a little above, far
   * enough back that all of it is in view: the sphere of the arm's reach around its base, cut
   * at the floor once the workspace is known. The arm stays in view in every pose; a hand
   * that turns the view keeps its distance (and is never re-aimed). */
  frame() {
    if (!this.controls) return;
    this.scene.updateMatrixWorld(true);
    const base = this.commanded.root.getWorldPosition(new THREE.Vector3());
    const reach = Math.max(this.commanded.reach, 0.1);
    const floor = Number.isFinite(this.floor) ? Math.min(Math.max(this.floor, -reach), reach / 2) : -reach;
    const points = reachable(reach, floor).map((point) => point.add(base));
    const back = new THREE.Vector3(0.7, 0.5, 0.9).normalize(); // from the target to the camera
    // The target: a point above the base, at the height that lets the camera come closest.
    let best = null;
    for (let step = 0; step <= 8; step++) {
      const target = base.clone().setY(base.y + floor + ((reach - floor) * step) / 16);
      const distance = this.distanceToShow(points, target, back);
      if (!best || distance < best.distance) best = { target, distance };
    }
    const distance = best.distance * 1.05; // the samples lie a little inside the surface
    this.controls.target.copy(best.target);
    this.camera.position.copy(best.target).addScaledVector(back, distance);
    this.camera.far = Math.max(10, distance * 4);
    this.camera.updateProjectionMatrix();
    this.controls.update();
  }

  /** How far back along `back` from `target` the camera must stand to have every one of
   * `points` in view. A point is in view when its offset across the view is within its depth
   * times the half-view's tangent, its depth being distance - (point - target)·back. */
  distanceToShow(points, target, back) {
    this.camera.position.copy(target).add(back);
    this.camera.lookAt(target);
    const right = new THREE.Vector3(1, 0, 0).applyQuaternion(this.camera.quaternion);
    const up = new THREE.Vector3(0, 1, 0).applyQuaternion(this.camera.quaternion);
    const tanHeight = Math.tan(THREE.MathUtils.degToRad(this.camera.fov / 2));
    const tanWidth = tanHeight * this.camera.aspect;
    const offset = new THREE.Vector3();
    let distance = 0;
    for (const point of points) {
      offset.subVectors(point, target);
      const across = Math.max(
        Math.abs(offset.dot(right)) / tanWidth,
        Math.abs(offset.dot(up)) / tanHeight,
      );
      distance = Math.max(distance, offset.dot(back) + across);
    }
    return distance;
  }

  /** How far the solid arm's furthest joint or tip is from the view's centre: 0 at the centre,
   * 1 at the view's edge (more: outside). For the browser tests and anyone reading the page. */
  armInView() {
    this.commanded.root.updateMatrixWorld(true);
    this.camera.updateMatrixWorld(true);
    let furthest = 0;
    for (const link of this.commanded.linkObjects.values()) {
      const at = link.getWorldPosition(new THREE.Vector3()).project(this.camera);
      furthest = Math.max(furthest, Math.abs(at.x), Math.abs(at.y));
    }
    return furthest.toFixed(3);
  }

  render() {
    if (!this.renderer || this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.renderer.render(this.scene, this.camera);
      // Where the view is from, for the browser tests (a hand's orbit is kept).
      this.container.dataset.camera = this.camera.position.toArray().map((v) => v.toFixed(3)).join(",");
    });
  }

  dispose() {
    if (this.renderer) this.renderer.dispose();
    if (this.controls) this.controls.dispose();
    this.container.replaceChildren();
  }
}
