// The guided calibration of a robot's hardware arm (a usb-slave), over the calibration REST
// endpoints (specs/api.md), LeRobot's way: 1. torque off, the person poses the arm like the twin
// (its solid arm: the robot's commanded pose), and captures it; 2. each joint is moved through
// its whole range while the card shows how far each has gone (the twin's ghost shows the
// measured arm live); 3. finish stores it, torque back on where the arm is. Cancel goes back to
// the calibration in use.

import { call, callReporting } from "./api.js";

const $ = (id) => document.getElementById(id);

const STEPS = {
  none: "Pose the arm like the twin's solid arm, step by step: Calibrate starts (torque goes off).",
  posing: "1 of 2. Torque is off: pose the arm by hand like the twin's solid arm, then Capture.",
  range: "2 of 2. Move each joint, one at a time, through its whole range, then Finish.",
};

let robot = null; // {id, slave, joints} of the card shown, with a hardware arm
let asked = 0; // counts status requests...
let answered = 0; // ...and the newest shown: an older answer that comes late is not

function path(action = "") {
  return `/api/robots/${encodeURIComponent(robot.id)}/calibration${action}`;
}

/** A joint's range so far, as a share of its limits, in a bar with its numbers. */
function rangeRow(name, [low, high], limits) {
  const item = document.createElement("li");
  item.dataset.joint = name;
  const span = limits ? limits.upper - limits.lower : 0;
  const meter = document.createElement("meter");
  meter.min = 0;
  meter.max = 1;
  meter.value = span > 0 ? Math.min(1, (high - low) / span) : 0;
  const text = document.createElement("span");
  text.textContent = `${name}: ${low.toFixed(1)} to ${high.toFixed(1)}`;
  item.append(text, meter);
  return item;
}

function render(status) {
  const session = status.session;
  const phase = session ? session.phase : "none";
  const state = status.calibrated ? `calibrated (${status.file})` : "not calibrated";
  $("calibration-step").textContent = session ? STEPS[phase] : `${state}. ${STEPS.none}`;
  $("calibrate-start").disabled = Boolean(session);
  $("calibrate-capture").disabled = phase !== "posing";
  $("calibrate-finish").disabled = phase !== "range";
  $("calibrate-cancel").disabled = !session;
  const limits = new Map(robot.joints.map((joint) => [joint.name, joint.limits]));
  const ranges = phase === "range" ? Object.entries(session.range) : [];
  $("calibration-ranges").replaceChildren(
    ...ranges.map(([name, range]) => rangeRow(name, range, limits.get(name))),
  );
}

async function refresh() {
  if (!robot) return;
  const mine = ++asked;
  const id = robot.id;
  const current = () => mine > answered && robot !== null && robot.id === id;
  try {
    const status = await call("GET", `${path()}?slave=${encodeURIComponent(robot.slave)}`);
    if (!current()) return;
    answered = mine;
    render(status);
  } catch (error) {
    if (!current()) return;
    answered = mine;
    $("calibration-step").textContent = `${error.code}: ${error.message}`;
  }
}

/** Show the flow for a robot's details: only with a hardware arm; its status fetched anew
 * (the card's refresh calls this every second: a range bar follows the arm). */
export function showCalibration(summary) {
  const arm = summary.slaves.find((slave) => slave.type === "usb-slave");
  $("calibration").hidden = !arm;
  robot = arm ? { id: summary.id, slave: arm.id, joints: summary.joints } : null;
  refresh();
}

export function closeCalibration() {
  robot = null;
  $("calibration").hidden = true;
}

/** Wire the buttons; `report(text, isError)` hears what went wrong. */
export function wireCalibration(report) {
  const step = async (action, body = {}) => {
    if (!robot) return;
    await callReporting(report, "POST", path(`/${action}`), { slave: robot.slave, ...body });
    await refresh();
  };
  $("calibrate-start").addEventListener("click", () => step("start"));
  $("calibrate-capture").addEventListener("click", () => step("capture"));
  $("calibrate-finish").addEventListener("click", () =>
    step("finish", { writeHoming: $("calibrate-homing").checked }),
  );
  $("calibrate-cancel").addEventListener("click", () => step("cancel"));
}
