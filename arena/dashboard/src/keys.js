// The keyboard as a source of the hand's velocity (drive.js): arrow keys move the hand along
// the base frame's x (up/down) and y (left/right), W/S along z; O/C open and close the gripper.

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

export class KeyboardSource {
  constructor() {
    this.held = new Set();
    this.changed = () => {};
    this.down = (event) => this.key(event, true);
    this.up = (event) => this.key(event, false);
    this.blur = () => this.held.clear(); // a key let go elsewhere is never heard here
  }

  attach() {
    window.addEventListener("keydown", this.down);
    window.addEventListener("keyup", this.up);
    window.addEventListener("blur", this.blur);
  }

  detach() {
    this.held.clear();
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
    if (this.held.size !== was) this.changed();
  }

  velocity() {
    if (!this.held.size) return null;
    const velocity = [0, 0, 0, 0];
    for (const name of this.held) {
      const [axis, sign] = KEYS[name];
      velocity[axis] += sign;
    }
    return velocity;
  }
}
