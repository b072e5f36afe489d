// What a master this page started is playing. The server names a master by its id and type
// only, so the page keeps what it asked for ("Playing Gentle Wave Pattern ...") by robot,
// master id and type, in this tab's session storage: a reload still knows, other tabs do not.
// A restarted server counts its masters' ids afresh: entries of an earlier run are not used.

const KEY = "arena.playing";
const MAX_ENTRIES = 50; // a long session starts many masters: keep the newest
const SAME_RUN_S = 5; // two start times this close (seconds) are one run of the server

let serverStarted = null; // when the server we talk to started (seconds since the epoch)

/** The server's `uptime_s`, as `GET /` says it now. */
export function setServerUptime(uptime) {
  serverStarted = Date.now() / 1000 - uptime;
}

function entries() {
  try {
    const stored = JSON.parse(sessionStorage.getItem(KEY) || "[]");
    return Array.isArray(stored) ? stored : [];
  } catch {
    return [];
  }
}

function matches(entry, robotId, master) {
  const [robot, id, type, started] = entry;
  return robot === robotId && id === master.id && type === master.type &&
    serverStarted !== null && Math.abs(started - serverStarted) < SAME_RUN_S;
}

/** Remember that `master` ({id, type}) of robot `robotId` plays what `text` says. */
export function rememberPlaying(robotId, master, text) {
  const kept = entries().filter((entry) => !matches(entry, robotId, master));
  kept.push([robotId, master.id, master.type, serverStarted, text]);
  sessionStorage.setItem(KEY, JSON.stringify(kept.slice(-MAX_ENTRIES)));
}

/** What `master` ({id, type}) of robot `robotId` plays, if this tab started it; else null. */
export function recallPlaying(robotId, master) {
  const found = entries().findLast((entry) => matches(entry, robotId, master));
  return found ? found[4] : null;
}

/** Forget what masters of robot `robotId` played (it was deleted; its ids start afresh). */
export function forgetRobot(robotId) {
  const kept = entries().filter(([robot]) => robot !== robotId);
  sessionStorage.setItem(KEY, JSON.stringify(kept));
}
