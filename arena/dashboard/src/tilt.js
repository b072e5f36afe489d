// A phone's tilt as a source of the hand's velocity (drive.js), from the browser's
// DeviceOrientation events, only while a finger holds a clutch button. Holding "Move", tipping
// the phone's top away moves the hand forward (x) and tipping its right edge down moves it to
// the right (-y); holding "Lift", tipping the top back toward you raises it (z). The phone's
// attitude when the button was pressed is the neutral one, so it may be held any way.

const DEAD_DEGREES = 5; // a hand's tremor moves nothing
const FULL_DEGREES = 30; // full speed from this far off neutral

/** `degrees` off neutral as a fraction of full speed (0 within the dead band). */
function tilt(degrees) {
  const size = Math.abs(degrees);
  if (!(size > DEAD_DEGREES)) return 0;
  const full = FULL_DEGREES - DEAD_DEGREES;
  return (Math.sign(degrees) * Math.min(size - DEAD_DEGREES, full)) / full;
}

/** `b - a` for angles in degrees, within (-180, 180] (beta wraps at ±180). */
function turned(a, b) {
  const difference = (((b - a) % 360) + 360) % 360;
  return difference > 180 ? difference - 360 : difference;
}

export class TiltSource {
  /** `row` is shown while driving; `move` and `lift` are its clutch buttons. */
  constructor(row, move, lift) {
    this.row = row;
    this.changed = () => {};
    this.note = () => {};
    this.latest = null; // {beta, gamma} of the newest event
    this.reference = null; // ...when the clutch was pressed
    this.clutch = null; // "move", "lift" or null
    this.oriented = (event) => this.orientation(event);
    for (const [button, clutch] of [
      [move, "move"],
      [lift, "lift"],
    ]) {
      button.addEventListener("pointerdown", (event) => this.hold(event, clutch));
      for (const name of ["pointerup", "pointercancel", "lostpointercapture"]) {
        button.addEventListener(name, () => this.letGo(clutch));
      }
      button.addEventListener("contextmenu", (event) => event.preventDefault()); // long press
    }
  }

  attach() {
    this.row.hidden = false;
    window.addEventListener("deviceorientation", this.oriented);
  }

  detach() {
    this.row.hidden = true;
    this.clutch = this.reference = null;
    window.removeEventListener("deviceorientation", this.oriented);
  }

  hold(event, clutch) {
    event.preventDefault();
    if (event.target.setPointerCapture) event.target.setPointerCapture(event.pointerId);
    // iOS asks the person, once, and only from a gesture such as this press.
    const Orientation = window.DeviceOrientationEvent;
    if (Orientation && typeof Orientation.requestPermission === "function") {
      Orientation.requestPermission().catch(() => this.note("tilt refused by the browser"));
    }
    this.clutch = clutch;
    this.reference = this.latest;
  }

  letGo(clutch) {
    if (this.clutch !== clutch) return;
    this.clutch = this.reference = null;
    this.changed(); // the stop goes at once
  }

  orientation(event) {
    if (event.beta === null || event.gamma === null) return; // no sensor
    this.latest = { beta: event.beta, gamma: event.gamma };
    if (this.clutch && !this.reference) this.reference = this.latest;
  }

  velocity() {
    if (!this.clutch || !this.reference || !this.latest) return null;
    const forward = tilt(-turned(this.reference.beta, this.latest.beta));
    if (this.clutch === "lift") return [0, 0, -forward, 0];
    return [forward, tilt(-turned(this.reference.gamma, this.latest.gamma)), 0, 0];
  }
}
