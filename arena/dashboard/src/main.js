// The dashboard's entry: the robot list, the selected robot (in the URL's #hash), the header's
// stop buttons, the API key, and the periodic refresh of what the sockets do not push.

import { ApiError, apiKey, call, callReporting, setApiKey } from "./api.js";
import { forgetRobot, rememberPlaying, setServerUptime } from "./playing.js";
import { RecordingsPanel } from "./recordings.js";
import { RobotView } from "./robot_view.js";

const $ = (id) => document.getElementById(id);
const REFRESH_MS = 1000;
const DEMO_ROBOT = "demo-arm"; // `arena serve --demo`'s robot: the one to show among several
const DEFAULT_NAME = "My Robot"; // the seed's name for a robot nobody named
const CHOOSE = "Choose a robot from the list.";

let view = null; // the RobotView of the selected robot
let robots = [];
let sequences = []; // the server's demo sequences, as `GET /api/sequences` lists them
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

const recordings = new RecordingsPanel({ selectedRobot: selectedId, report });

async function refresh() {
  const mine = ++refreshes;
  try {
    const status = await call("GET", "/");
    setServerUptime(status.uptime_s);
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
  } else {
    view.applySummary(summary);
  }
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

function closeView() {
  if (view) view.close();
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
    if (robot.estop_reason) state.title = robot.estop_reason;
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
    const robot = selectedId();
    const chosen = sequences.find((sequence) => sequence.id === $("sequence").value);
    if (!chosen) return;
    const path = `${robotPath()}/play-sequence/${encodeURIComponent(chosen.id)}`;
    const answer = await callReporting(report, "POST", path);
    if (!answer) return;
    const text = `Playing ${chosen.name} (${chosen.id}, ${chosen.duration / 1000} s)`;
    rememberPlaying(robot, { id: answer.master, type: "mock-sequence" }, text);
    await refresh();
  });
  // The seed's "connect demo sequences": every demo sequence, looping, as the robot's master.
  // A master that holds the robot is displaced only on a second click: the first asks without
  // taking over, and the server's MASTER_ACTIVE (naming the holder) arms the button.
  const connect = $("connect-demo");
  const label = connect.textContent;
  let disarm = null;
  connect.addEventListener("click", async () => {
    const robot = selectedId();
    const takeover = connect.dataset.armed === robot;
    clearTimeout(disarm);
    delete connect.dataset.armed;
    connect.textContent = label;
    let answer;
    try {
      answer = await call("POST", `/api/robots/${encodeURIComponent(robot)}/master`, {
        type: "mock-sequence",
        loop: true,
        takeover,
      });
    } catch (error) {
      report(`${error.code}: ${error.message}`, true);
      if (error.code === "MASTER_ACTIVE" && !takeover && selectedId() === robot) {
        connect.dataset.armed = robot;
        connect.textContent = "Take over with the demo sequences?";
        disarm = setTimeout(() => {
          delete connect.dataset.armed;
          connect.textContent = label;
        }, 4000);
      }
      return;
    }
    const ids = sequences.map((sequence) => sequence.id).join(", ");
    rememberPlaying(robot, answer, `Playing the demo sequences in a loop (${ids})`);
    await refresh();
  });
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
    const robot = selectedId();
    const answer = await act("DELETE", robotPath());
    if (answer) {
      forgetRobot(robot);
      location.hash = "";
    }
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
    let types;
    [types, sequences] = await Promise.all([
      call("GET", "/api/robot-types"),
      call("GET", "/api/sequences"),
    ]);
    $("create-robot").querySelector("button").disabled = !types.length;
    $("create-type").replaceChildren(
      ...types.map((type) => {
        const option = new Option(type.id, type.id);
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
window.addEventListener("hashchange", refresh);
fillChoices().then(refresh);
setInterval(refresh, REFRESH_MS);
