// A gamepad as a source of the hand's velocity (drive.js), read through the browser's Gamepad
// API on every tick of the driver. The standard mapping: the left stick moves the hand along x
// (up: forward) and y (left: to the left), the right stick's up and down along z; the left
// trigger opens the gripper, the right one closes it. A stick near its centre moves nothing
// (a dead zone: worn sticks rest a little off it), and past it the speed grows from zero.

const DEAD_ZONE = 0.15;
// Standard mapping: axes 0/1 the left stick, 2/3 the right one (y down); buttons 6/7 the
// left and right triggers (their `value` 0 to 1).
const LEFT_X = 0;
const LEFT_Y = 1;
const RIGHT_Y = 3;
const LEFT_TRIGGER = 6;
const RIGHT_TRIGGER = 7;

/** An axis with the dead zone taken out: 0 within it, then on to ±1 at full deflection. */
export function deadZoned(value) {
  const size = Math.abs(value);
  if (!Number.isFinite(value) || size <= DEAD_ZONE) return 0;
  return (Math.sign(value) * (Math.min(size, 1) - DEAD_ZONE)) / (1 - DEAD_ZONE);
}

export class GamepadSource {
  constructor() {
    this.changed = () => {};
    this.note = () => {};
    this.seen = null; // the id of the pad last read, to say so once
  }

  attach() {
    this.seen = null;
  }

  detach() {}

  /** The first connected pad (browsers show one only after a button is pressed on it). */
  pad() {
    const pads = navigator.getGamepads ? navigator.getGamepads() : [];
    return [...pads].find((pad) => pad && pad.connected) || null;
  }

  velocity() {
    const pad = this.pad();
    const id = pad ? pad.id : null;
    if (id !== this.seen) {
      this.seen = id;
      this.note(pad ? `gamepad: ${id}` : "");
    }
    if (!pad) return null;
    const axis = (index) => deadZoned(pad.axes[index] || 0);
    const trigger = (index) => deadZoned(pad.buttons[index] ? pad.buttons[index].value : 0);
    return [
      -axis(LEFT_Y),
      -axis(LEFT_X),
      -axis(RIGHT_Y),
      trigger(LEFT_TRIGGER) - trigger(RIGHT_TRIGGER),
    ];
  }
}
