// "Drive the hand": the keyboard, a gamepad and a phone's tilt steer the selected robot's hand
// over the master WebSocket with `ee_velocity` messages (specs/cartesian.md). Each input is a
// source of a velocity in fractions of full speed, [x, y, z, gripper] in the robot's base
// frame; the driver adds them up and, while the sum is not zero, sends it every 50 ms, then one
// stop. A page that goes quiet (a closed tab, a lost network) stops the hand within the
// robot's dead-man time anyway. While a master runs (a policy, a sequence), driving is an
// intervention (`?intervene=1`): that master waits, paused, and stopping hands it back.

import { apiKey } from "./api.js";

const SPEED = 0.05; // m/s of the hand at full deflection
const GRIP_SPEED = 50; // the gripper's unit (percent or degrees) per second
const SEND_MS = 50;

/** The driver of one robot's hand: `start(robotId, {intervene})`, `stop()`; `onStatus(text)`
 * hears what it is doing. `sources` have `velocity()` (an array of four, or null), `attach()`
 * and `detach()`; they call `changed()` for a message at once (a key let go) and `note(text)`
 * to say what they see (a gamepad). */
export class HandDriver {
  constructor(onStatus, sources) {
    this.onStatus = onStatus;
    this.sources = sources;
    this.socket = null;
    this.moving = false; // the last message sent was not a stop
    this.timer = null;
    this.help = "";
    for (const source of sources) {
      source.changed = () => this.send();
      source.note = (text) => this.note(text);
    }
  }

  get driving() {
    return this.socket !== null;
  }

  /** Take the robot: as its master, or (`intervene`) as an intervention on the running one. */
  start(robotId, { intervene = false } = {}) {
    this.stop();
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const key = apiKey();
    const query =
      `?id=dashboard-hand${intervene ? "&intervene=1" : ""}` +
      (key ? `&token=${encodeURIComponent(key)}` : "");
    const socket = new WebSocket(
      `${scheme}://${location.host}/ws/master/${encodeURIComponent(robotId)}${query}`,
    );
    this.socket = socket;
    this.help = intervene
      ? "correcting (the master waits; stop to hand back): arrows, W/S, O/C"
      : "driving: arrows, W/S, O/C";
    this.onStatus("connecting…");
    socket.addEventListener("open", () => {
      if (this.socket === socket) this.onStatus(this.help);
    });
    socket.addEventListener("message", (event) => {
      const message = JSON.parse(event.data);
      if (message.type === "error" || (message.type === "ack" && message.data.status === "refused")) {
        this.onStatus(`${message.data.code}: ${message.data.message}`);
      }
    });
    socket.addEventListener("close", (event) => {
      if (this.socket !== socket) return;
      this.release();
      this.onStatus(event.reason ? `stopped: ${event.reason}` : "stopped");
    });
    for (const source of this.sources) source.attach();
    this.timer = setInterval(() => this.send(), SEND_MS);
  }

  stop() {
    const socket = this.socket;
    this.release();
    if (socket && socket.readyState === WebSocket.OPEN) {
      socket.send('{"type":"release","data":{"hold":true}}');
    }
    if (socket) socket.close(1000);
  }

  release() {
    this.socket = null;
    this.moving = false;
    clearInterval(this.timer);
    for (const source of this.sources) source.detach();
  }

  /** A source's name beside the keys in the status (a gamepad seen, say). */
  note(text) {
    if (this.socket && this.socket.readyState === WebSocket.OPEN) {
      this.onStatus(text ? `${this.help}; ${text}` : this.help);
    }
  }

  /** The sources' velocity, each part within full speed; sent while it is not zero, and
   * once more (a stop) when it comes back to zero. */
  send() {
    const socket = this.socket;
    if (!socket || socket.readyState !== WebSocket.OPEN) return;
    const sum = [0, 0, 0, 0];
    for (const source of this.sources) {
      const velocity = source.velocity();
      if (velocity) velocity.forEach((value, axis) => (sum[axis] += value));
    }
    const clamped = sum.map((value) => Math.max(-1, Math.min(1, value)));
    const moving = clamped.some((value) => value !== 0);
    if (!moving && !this.moving) return;
    this.moving = moving;
    const data = { linear: clamped.slice(0, 3).map((value) => value * SPEED) };
    if (clamped[3]) data.gripper = clamped[3] * GRIP_SPEED;
    socket.send(JSON.stringify({ type: "ee_velocity", data }));
  }
}
