// Taking a robot over from its master takes a second click. The first asks without taking
// over; the server's MASTER_ACTIVE refusal (naming who holds the robot) is shown and arms what
// was clicked; a second click on it within the window asks with "takeover": true.

export const TAKEOVER_WINDOW_MS = 4000;

export class SecondClickTakeover {
  /** `onChange()` runs when what is armed changes (to relabel the buttons). */
  constructor(onChange) {
    this.onChange = onChange;
    this.key = null; // what is armed: a robot id, or a robot and a file
    this.timer = null;
  }

  /** Whether `key` was refused a moment ago, so that its next click takes over. */
  isArmed(key) {
    return this.key === key;
  }

  /**
   * Run `send(takeover)` for `key` (it calls the API and returns its answer). A MASTER_ACTIVE
   * refusal of a request that did not take over arms `key`, if `stillWanted()` (the page
   * still shows what was clicked). Errors go to `report(text, isError)`; answers null then.
   */
  async request(key, send, { report, holder = () => "", stillWanted = () => true }) {
    const takeover = this.isArmed(key);
    this.disarm();
    try {
      return await send(takeover);
    } catch (error) {
      const held = error.code === "MASTER_ACTIVE" ? holder() : "";
      const again = error.code === "MASTER_ACTIVE" && !takeover && stillWanted();
      report(
        `${error.code}: ${error.message}` +
          (held ? ` It is held by ${held}.` : "") +
          (again ? ` Click again within ${TAKEOVER_WINDOW_MS / 1000} s to take over.` : ""),
        true,
      );
      if (again) this.arm(key);
      return null;
    }
  }

  arm(key) {
    this.key = key;
    this.timer = setTimeout(() => this.disarm(), TAKEOVER_WINDOW_MS);
    this.onChange();
  }

  disarm() {
    clearTimeout(this.timer);
    if (this.key === null) return;
    this.key = null;
    this.onChange();
  }
}
