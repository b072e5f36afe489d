// "Drive the hand": the keyboard steers the selected robot's hand over the master WebSocket
// with `ee_velocity` messages (specs/cartesian.md). Arrow keys move it along the base frame's
// x (up/down) and y (left/right), W/S along z; O/C open and close the gripper. While a key is
// held a message goes every 50 ms; letting go sends a stop, and a page that goes quiet (a
// closed tab, a lost network) stops the hand within the robot's dead-man time anyway.

import { apiKey } from "./api.js";

const SPEED = 0.05; // m/s of the hand
const GRIP_SPEED = 50; // the gripper's unit (percent or degrees) per second
const SEND_MS = 50;
// key -> [axis, sign]; axis 3 is the gripper
const KEYS = {
  ArrowUp: [0, 1],
  ArrowDown: [0, -1],
  ArrowLeft: [1, 1],
  ArrowRight: [1, -1],
  w: [2, 1],
  s: [2, -1],
  o: [3, 1],
  c: [3, -1],
};

/** The keyboard driver of one robot's hand: `start(robotId)`, `stop()`; `onStatus(text)`
 * hears what it is doing. */
export class HandDriver {
  constructor(onStatus) {
    this.onStatus = onStatus;
    this.socket = null;
    this.held = new Set();
    this.timer = null;
    this.down = (event) => this.key(event, true);
    this.up = (event) => this.key(event, false);
    this.blur = () => this.held.clear(); // a key let go elsewhere is never heard here
  }

  get driving() {
    return this.socket !== null;
  }

  start(robotId) {
    this.stop();
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const key = apiKey();
    const query = `?id=dashboard-hand${key ? `&token=${encodeURIComponent(key)}` : ""}`;
    const socket = new WebSocket(
      `${scheme}://${location.host}/ws/master/${encodeURIComponent(robotId)}${query}`,
    );
    this.socket = socket;
    this.onStatus("connecting…");
    socket.addEventListener("open", () => {
      if (this.socket === socket) this.onStatus("driving: arrows, W/S, O/C");
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
    window.addEventListener("keydown", this.down);
    window.addEventListener("keyup", this.up);
    window.addEventListener("blur", this.blur);
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
    this.held.clear();
    clearInterval(this.timer);
    window.removeEventListener("keydown", this.down);
    window.removeEventListener("keyup", this.up);
    window.removeEventListener("blur", this.blur);
  }

  key(event, pressed) {
    const name = event.key.length === 1 ? event.key.toLowerCase() : event.key;
    if (!(name in KEYS) || event.target.closest("input, textarea, select")) return;
    event.preventDefault(); // arrows would scroll the page
    const was = this.held.size;
    if (pressed) this.held.add(name);
    else this.held.delete(name);
    if (this.held.size !== was) this.send(true);
  }

  /** The velocity of the keys held; sent while any is, and once more (a stop) when the
   * last is let go (`changed`). */
  send(changed = false) {
    const socket = this.socket;
    if (!socket || socket.readyState !== WebSocket.OPEN || (!this.held.size && !changed)) return;
    const velocity = [0, 0, 0, 0];
    for (const name of this.held) {
      const [axis, sign] = KEYS[name];
      velocity[axis] += sign * (axis === 3 ? GRIP_SPEED : SPEED);
    }
    const data = { linear: velocity.slice(0, 3) };
    if (velocity[3]) data.gripper = velocity[3];
    socket.send(JSON.stringify({ type: "ee_velocity", data }));
  }
}
