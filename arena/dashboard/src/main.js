// The dashboard's entry: the robot list, the selected robot (in the URL's #hash), the header's
// stop buttons, the API key, and the periodic refresh of what the sockets do not push.

import { ApiError, apiKey, call, callReporting, setApiKey } from "./api.js";
import { showPolicies, wireAttach } from "./attach.js";
import { closeCalibration, wireCalibration } from "./calibrate.js";
import { HandDriver } from "./drive.js";
import { GamepadSource } from "./gamepad.js";
import { KeyboardSource } from "./keys.js";
import { LeaderPanel } from "./leader.js";
import { RecordingsPanel } from "./recordings.js";
import { masterText, RobotView } from "./robot_view.js";
import { SecondClickTakeover } from "./takeover.js";
import { TiltSource } from "./tilt.js";

const $ = (id) => document.getElementById(id);
const REFRESH_MS = 1000;
const DEMO_ROBOT = "demo-arm"; // `arena serve --demo`'s robot: the one to show among several
const DEFAULT_NAME = "My Robot"; // the seed's name for a robot nobody named
const CHOOSE = "Choose a robot from the list.";

let view = null; // the RobotView of the selected robot
let robots = [];
let creating = false; // a robot is being created: no other is opened meanwhile
let refreshes = 0; // counts refreshes: an older one that ends late changes nothing

function selectedId() {
  const match = location.hash.match(/^#\/robots\/(.+)$/);
  return match ? decodeURIComponent(match[1]) : null;
}

function report(text, isError = false) {
  if (view) view.log(text, isError);
  $("notice").textContent = text;
  $("notice").className = isError ? "error" : "muted";
}

// Connect demo sequences and Replay take a robot over from its master on a second click;
// one thing is armed at a time.
const CONNECT_LABEL = "Connect demo sequences";
const takeover = new SecondClickTakeover(() => {
  const armed = takeover.isArmed(selectedId());
  $("connect-demo").textContent = armed ? "Take over with the demo sequences?" : CONNECT_LABEL;
  $("connect-demo").classList.toggle("armed", armed);
  recordings.showArmed();
});

/** Who holds the selected robot, in words (as `masterText` says it), as far as known. */
function holder() {
  const master = view && view.robotId === selectedId() ? view.master() : null;
  return master ? masterText(master) : "";
}

const recordings = new RecordingsPanel({ selectedRobot: selectedId, report, takeover, holder });
const leader = new LeaderPanel(report);

async function refresh() {
  const mine = ++refreshes;
  try {
    const status = await call("GET", "/");
    $("server-status").textContent =
      `${status.robots} robot${status.robots === 1 ? "" : "s"}, ` +
      `recording ${status.recording.active ? (status.recording.error ? "FAILING" : "on") : "off"}` +
      `${status.auth ? ", keys on" : ""}`;
    robots = await call("GET", "/api/robots");
    if (status.fleet) {
      // In a fleet: every node's robots, each opened through this server whichever owns it.
      const local = new Set(robots.map((robot) => robot.id));
      const fleet = await call("GET", "/api/fleet/robots");
      for (const robot of fleet.robots) {
        if (local.has(robot.id)) robots.find((r) => r.id === robot.id).node = robot.node;
        else robots.push({ ...robot, remote: true });
      }
    }
  } catch (error) {
    $("server-status").textContent = `${error.code}: ${error.message}`;
    if (error instanceof ApiError && error.status === 401 && !apiKey()) $("key-dialog").showModal();
    return;
  }
  if (mine !== refreshes || creating) return; // a newer refresh, or a new robot, will show
  chooseForTheVisitor();
  showRobotList();
  const id = selectedId();
  let summary = robots.find((robot) => robot.id === id);
  if (summary && summary.remote) {
    // another node's robot: its details come through this server (the fleet forwards them)
    summary = summary.state === "offline" ? null : await call("GET", `/api/robots/${encodeURIComponent(id)}`);
    if (mine !== refreshes || creating) return;
  }
  if (!summary) {
    if (view) closeView();
  } else if (!view || view.robotId !== id) {
    closeView();
    view = new RobotView(summary, { onChanged: () => refresh() });
    $("robot-panel").hidden = false;
    showPolicies(id);
  } else {
    view.applySummary(summary);
  }
  if (summary && !summary.remote) await leader.refresh(id, summary);
  await recordings.refresh();
}

/** With no robot chosen, open the one there is, or the demo robot; among several, say so. */
function chooseForTheVisitor() {
  if (selectedId() !== null) {
    if ($("notice").textContent === CHOOSE) $("notice").textContent = "";
    return;
  }
  const only = robots.length === 1 ? robots[0] : robots.find((robot) => robot.id === DEMO_ROBOT);
  if (only) {
    // replace, not push: the back button leaves the page instead of coming back here
    history.replaceState(null, "", `#/robots/${encodeURIComponent(only.id)}`);
  } else if (robots.length && !view) {
    report(CHOOSE);
  }
}

// "Drive the hand" (drive.js): the keyboard, a gamepad and a phone's tilt as the robot's
// master while it is on, or as an intervention on the master that runs.
const hand = new HandDriver(
  (text) => {
    $("drive-status").textContent = text;
    $("drive-hand").textContent = hand.driving ? "Stop driving" : "Drive the hand";
  },
  [
    new KeyboardSource(),
    new GamepadSource(),
    new TiltSource($("tilt-row"), $("tilt-move"), $("tilt-lift")),
  ],
);

function closeView() {
  if (hand.driving) hand.stop();
  if (view) view.close();
  closeCalibration();
  leader.close();
  view = null;
  $("robot-panel").hidden = true;
  $("estop").disabled = true;
  $("reset").disabled = true;
}

function showRobotList() {
  const list = $("robot-list");
  list.replaceChildren();
  for (const robot of robots) {
    const item = document.createElement("li");
    item.dataset.robot = robot.id;
    if (robot.id === selectedId()) item.className = "selected";
    const link = document.createElement("a");
    link.href = `#/robots/${encodeURIComponent(robot.id)}`;
    const id = document.createElement("span");
    id.className = "id";
    id.textContent = robot.id; // names need not differ: ids do
    link.append(`${robot.name} `, id);
    const state = document.createElement("span");
    state.className = `state ${robot.state}`;
    state.textContent = robot.master ? `${robot.state} by ${robot.master.id}` : robot.state;
    state.title = robot.estop_reason || (robot.master ? masterText(robot.master) : "");
    item.append(link, state);
    if (robot.node) {
      const node = document.createElement("span");
      node.className = "muted";
      node.dataset.node = robot.node;
      node.textContent = `@${robot.node}`;
      item.append(node);
    }
    list.append(item);
  }
  if (!robots.length) list.innerHTML = '<li class="muted">no robots yet</li>';
}

async function act(method, path, body) {
  const answer = await callReporting(report, method, path, body);
  if (answer !== null) await refresh();
  return answer;
}

function wireHeader() {
  $("estop").addEventListener("click", () =>
    act("POST", `/api/robots/${encodeURIComponent(selectedId())}/estop`, {
      reason: "e-stop from the dashboard",
    }),
  );
  $("stop-all").addEventListener("click", () =>
    act("POST", "/api/estop", { reason: "stop-everything from the dashboard" }),
  );
  $("reset").addEventListener("click", () =>
    act("POST", `/api/robots/${encodeURIComponent(selectedId())}/reset`),
  );
  $("key-button").addEventListener("click", () => {
    $("key-input").value = apiKey();
    $("key-dialog").showModal();
  });
  // Keep the key at the click itself: a request failing meanwhile must not ask again.
  $("key-save").addEventListener("click", () => setApiKey($("key-input").value.trim()));
  $("key-dialog").addEventListener("close", () => {
    if ($("key-dialog").returnValue === "save") {
      closeView(); // sockets reopen with the new key
      fillChoices().then(refresh);
    }
  });
}

function wireRobotControls() {
  const robotPath = () => `/api/robots/${encodeURIComponent(selectedId())}`;
  $("create-robot").addEventListener("submit", (event) => {
    event.preventDefault();
    createRobot();
  });
  $("play").addEventListener("click", async () => {
    const chosen = $("sequence").value;
    if (!chosen) return;
    await act("POST", `${robotPath()}/play-sequence/${encodeURIComponent(chosen)}`);
  });
  // The seed's "connect demo sequences": every demo sequence, looping, as the robot's master;
  // it takes over from a master that holds the robot only on a second click.
  $("connect-demo").addEventListener("click", async () => {
    const robot = selectedId();
    const answer = await takeover.request(
      robot,
      (asked) =>
        call("POST", `/api/robots/${encodeURIComponent(robot)}/master`, {
          type: "mock-sequence",
          loop: true,
          takeover: asked,
        }),
      { report, holder, stillWanted: () => selectedId() === robot },
    );
    if (answer) await refresh();
  });
  $("drive-hand").addEventListener("click", () => {
    const mode = view && view.state ? view.state.mode : "";
    if (hand.driving) hand.stop();
    else hand.start(selectedId(), { intervene: mode === "mastered" || mode === "paused" });
    $("drive-hand").textContent = hand.driving ? "Stop driving" : "Drive the hand";
  });
  wireAttach({ robotPath, mode: () => (view && view.state ? view.state.mode : ""), act });
  $("stop-sequence").addEventListener("click", () => act("POST", `${robotPath()}/stop-sequence`));
  $("add-mock").addEventListener("click", () =>
    act("POST", `${robotPath()}/slaves`, { type: "mock-slave" }),
  );
  $("add-usb").addEventListener("click", () => {
    const port = $("usb-port").value.trim();
    act("POST", `${robotPath()}/slaves`, port ? { type: "usb-slave", port } : { type: "usb-slave" });
  });
  $("add-camera").addEventListener("click", () =>
    act("POST", `${robotPath()}/cameras`, {
      name: $("camera-name").value.trim(),
      source: $("camera-source").value.trim(),
    }),
  );
  $("episode-start").addEventListener("click", () =>
    act("POST", `${robotPath()}/episodes/start`, {
      task: $("episode-task").value.trim() || "teleoperation",
    }),
  );
  $("episode-stop").addEventListener("click", () => act("POST", `${robotPath()}/episodes/stop`));
  $("master-pause").addEventListener("click", () => act("POST", `${robotPath()}/master/pause`));
  $("master-resume").addEventListener("click", () => act("POST", `${robotPath()}/master/resume`));
  $("intervene").addEventListener("click", async () => {
    const shown = view;
    const answer = await act("POST", `${robotPath()}/intervention`, {});
    if (answer && shown === view && view) {
      view.intervening = true; // the sliders are this page's now (its PUT .../joints)
      if (view.state) view.applyState(view.state);
    }
  });
  $("hand-back").addEventListener("click", () => act("DELETE", `${robotPath()}/intervention`));
  // Space pauses and resumes the master for whoever has the page focused (not while typing,
  // nor on a button, which space presses by itself).
  document.addEventListener("keydown", (event) => {
    if (event.key !== " " || !view || !view.state) return;
    if (event.target.closest && event.target.closest("input, select, textarea, button, dialog")) return;
    const mode = view.state.mode;
    if (mode !== "mastered" && mode !== "paused") return;
    event.preventDefault();
    act("POST", `${robotPath()}/master/${mode === "mastered" ? "pause" : "resume"}`);
  });
  $("episode-discard").addEventListener("click", () => act("POST", `${robotPath()}/episodes/discard`));
  // Deleting needs a second click on the same button: no modal dialog to dismiss on a phone.
  const remove = $("delete-robot");
  remove.addEventListener("click", async () => {
    if (!remove.dataset.armed) {
      remove.dataset.armed = "1";
      remove.textContent = "Really delete?";
      setTimeout(() => {
        delete remove.dataset.armed;
        remove.textContent = "Delete robot";
      }, 4000);
      return;
    }
    const answer = await act("DELETE", robotPath());
    if (answer) location.hash = "";
  });
}

/** Create a robot from the form (a name is optional), attach the chosen slave, open it. */
async function createRobot() {
  if (creating) return; // a second click while the first is under way makes no second robot
  // Close the robot on screen at once: what is clicked next must be the new robot's.
  creating = true;
  closeView();
  try {
    const body = {
      robot_type: $("create-type").value,
      name: $("create-name").value.trim() || DEFAULT_NAME,
    };
    const id = $("create-id").value.trim();
    if (id) body.id = id;
    const slave = $("create-slave").value;
    const robot = await callReporting(report, "POST", "/api/robots", body);
    if (!robot) return;
    $("create-robot").reset();
    const path = `/api/robots/${encodeURIComponent(robot.id)}/slaves`;
    if (slave) await callReporting(report, "POST", path, { type: slave });
    history.pushState(null, "", `#/robots/${encodeURIComponent(robot.id)}`);
  } finally {
    creating = false;
    await refresh();
  }
}

async function fillChoices() {
  try {
    const [types, sequences] = await Promise.all([
      call("GET", "/api/robot-types"),
      call("GET", "/api/sequences"),
    ]);
    $("create-robot").querySelector("button").disabled = !types.length;
    $("create-type").replaceChildren(
      ...types.map((type) => {
        // the API's default type (a create body without `robot_type`) is the form's default,
        // also after the form is reset: not the first in the list
        const isDefault = type.id === "so-arm100";
        const option = new Option(type.id, type.id, isDefault, isDefault);
        option.title = type.description;
        return option;
      }),
    );
    $("sequence").replaceChildren(
      ...sequences.map((sequence) => new Option(`${sequence.name} (${sequence.duration / 1000} s)`, sequence.id)),
    );
  } catch (error) {
    report(`${error.code}: ${error.message}`, true);
  }
}

wireHeader();
wireRobotControls();
wireCalibration(report);
window.addEventListener("hashchange", () => {
  takeover.disarm(); // armed for the robot that was on screen
  refresh();
});
fillChoices().then(refresh);
setInterval(refresh, REFRESH_MS);
