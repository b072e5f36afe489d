// One robot's panel: state, sliders, live virtual and real values, the 3D twin, sequences,
// master and slaves, recent events. Everything goes through the public API.

import { apiKey, call, callReporting, watchRobot } from "./api.js";
import { showAttach } from "./attach.js";
import { showCalibration } from "./calibrate.js";
import { showFlywheel } from "./flywheel.js";
import { COMMANDED_COLOR, cssColor, MEASURED_COLOR, Twin } from "./twin.js";

const $ = (id) => document.getElementById(id);

// Slider commands go out at most this often (ms), newest value wins: well under the robot's
// command rate limit, and smooth enough for a hand on a slider.
const SEND_INTERVAL = 50;
const MAX_EVENTS = 30;
// Masters that play something by themselves (the master line says "Playing ...").
const PLAYERS = new Set(["mock-sequence", "replay"]);

/** The two things a COLLISION refusal names ("... would bring lower_arm and floor together"). */
function collidingParts(message) {
  const found = /bring (\S+) and (\S+) together/.exec(message);
  return found ? [found[1], found[2]] : [];
}

function degrees(value) {
  return value === null || value === undefined ? "–" : value.toFixed(1);
}

/** Who is attached, in the seed's words: "Master + Slaves" when both are. */
function attachedText(summary) {
  const master = Boolean(summary.master);
  const slaves = summary.slaves.length > 0;
  if (master && slaves) return "Master + Slaves";
  if (master) return "Master, no slave";
  if (slaves) return "Slaves, no master";
  return "No master, no slave";
}

/** A WebSocket master's link beside it: green, amber or red (the server's `quality`), with
 * its round trip, jitter and the commands dropped for arriving too late. */
export function linkTag(link) {
  const ms = (seconds) => (seconds == null ? "?" : `${Math.round(seconds * 1000)}`);
  const tag = document.createElement("span");
  tag.className = `tag link ${link.quality}`;
  tag.textContent = `link ${ms(link.rtt)} ms ±${ms(link.jitter)}` + (link.dropped_stale ? `, ${link.dropped_stale} stale` : "");
  tag.title =
    `${link.quality}: round trip ${ms(link.rtt)} ms, jitter ${ms(link.jitter)} ms, ` +
    `${link.dropped_stale} commands dropped for arriving over ${ms(link.max_age)} ms old`;
  return tag;
}

/** What a master is, in the server's words: "sequence 'gentle-wave' (master 'master-3',
 * mock-sequence)"; without a description, "master 'alice' (websocket)". */
export function masterText(master) {
  const kind = master.kind || master.type;
  return master.description
    ? `${master.description} (master '${master.id}', ${kind})`
    : `master '${master.id}' (${kind})`;
}

/** Colour the twin legend's swatches as the twin draws the arms. */
function colourLegend() {
  const solid = document.querySelector('#twin-legend [data-part="commanded"] .swatch');
  solid.style.borderColor = solid.style.background = cssColor(COMMANDED_COLOR);
  const ghost = document.querySelector('#twin-legend [data-part="measured"] .swatch');
  ghost.style.borderColor = cssColor(MEASURED_COLOR);
  ghost.style.background = cssColor(MEASURED_COLOR, 0.15);
}

export class RobotView {
  constructor(summary, { onChanged }) {
    this.robotId = summary.id;
    this.onChanged = onChanged;
    this.state = null;
    this.summary = summary;
    this.sliders = new Map();
    this.pending = new Map(); // joint -> value not yet sent
    this.sending = false;
    this.closed = false;
    this.intervening = false; // this page's operator intervenes (its sliders drive)
    colourLegend();
    this.buildJoints(summary.joints);
    this.applySummary(summary);
    this.watcher = watchRobot(
      this.robotId,
      (type, data) => this.onMessage(type, data),
      (status) => {
        $("watch-status").textContent = status === "connected" ? "live" : status;
      },
    );
    Twin.create($("twin"), summary.robot_type)
      .then((twin) => {
        if (this.closed) {
          twin.dispose();
          return;
        }
        this.twin = twin;
        twin.setMeasuring(this.summary.slaves.length > 0);
        if (this.lastJoints) twin.show(this.lastJoints);
        return this.showWorkspace();
      })
      .catch((error) => this.log(`3D view: ${error.message}`, true));
  }

  close() {
    this.closed = true;
    this.watcher.close();
    if (this.twin) this.twin.dispose();
    $("twin").replaceChildren();
    $("cameras").replaceChildren(); // closes the streams
  }

  /** One table row per joint: name, slider within the model's limits, virtual, real. */
  buildJoints(joints) {
    const body = $("joints").querySelector("tbody");
    body.replaceChildren();
    for (const joint of joints) {
      const row = document.createElement("tr");
      const slider = document.createElement("input");
      slider.type = "range";
      slider.min = joint.limits.lower;
      slider.max = joint.limits.upper;
      slider.step = 0.5;
      slider.value = joint.virtual_value;
      slider.dataset.joint = joint.name;
      slider.setAttribute("aria-label", joint.name);
      slider.addEventListener("input", () => this.queue(joint.name, Number(slider.value)));
      // While a hand is on it, the slider shows the hand's value, not the robot's.
      slider.addEventListener("pointerdown", () => (slider.dataset.held = "1"));
      slider.addEventListener("pointerup", () => delete slider.dataset.held);
      slider.addEventListener("blur", () => delete slider.dataset.held);
      const cells = [joint.name, slider, "", ""].map((content) => {
        const cell = document.createElement("td");
        cell.append(content);
        return cell;
      });
      cells[2].className = cells[3].className = "value";
      cells[2].dataset.virtual = joint.name;
      cells[3].dataset.real = joint.name;
      row.append(...cells);
      body.append(row);
      this.sliders.set(joint.name, { slider, label: cells[0], virtual: cells[2], real: cells[3] });
    }
    this.showJoints(joints);
    call("GET", `/api/robot-types/${encodeURIComponent(this.summary.robot_type)}`)
      .then((type) => this.showUnits(type.joints))
      .catch((error) => this.log(`robot type: ${error.message}`, true));
  }

  /** Each joint's unit as its robot type says: degrees, or 0 (closed) to 100 (open) for a
   * LeRobot gripper (`unit: "percent"`), in the slider's row and its hint. */
  showUnits(specs) {
    if (this.closed) return;
    for (const spec of specs) {
      const entry = this.sliders.get(spec.name);
      if (!entry) continue;
      const unit = spec.unit === "percent" ? "%" : "°";
      entry.label.textContent = `${spec.name} (${unit})`;
      entry.slider.dataset.unit = spec.unit;
      entry.slider.title =
        spec.unit === "percent" ? "0 % closed, 100 % open" : `${spec.lower.toFixed(0)}° to ${spec.upper.toFixed(0)}°`;
    }
  }

  /** A new robot summary (polled): who is attached, and how they are doing. */
  applySummary(summary) {
    this.summary = summary;
    $("robot-title").textContent = `${summary.name} (${summary.id})`;
    const status = $("robot-status");
    status.textContent = attachedText(summary);
    status.title = [
      summary.master ? masterText(summary.master) : "no master",
      ...summary.slaves.map((slave) => `slave ${slave.id} (${slave.type})`),
    ].join(", ");
    if (this.twin) this.twin.setMeasuring(summary.slaves.length > 0);
    this.showLegend();
    if (!this.state) {
      this.applyState({
        mode: summary.state,
        owner: summary.owner,
        estop_reason: summary.estop_reason,
        master: summary.master,
      });
    }
    this.showMaster();
    showFlywheel(summary);
    showCalibration(summary);
    const peers = $("peers");
    peers.replaceChildren();
    const entries = [
      ...(summary.master ? [["master", summary.master]] : []),
      ...summary.slaves.map((slave) => ["slave", slave]),
    ];
    for (const [role, peer] of entries) {
      const item = document.createElement("li");
      item.dataset.peer = peer.id;
      const tag = document.createElement("span");
      tag.className = `tag ${peer.connected ? "up" : "down"}`;
      tag.textContent = peer.connected ? "connected" : "disconnected";
      const label = document.createElement("span");
      label.textContent = `${role}: ${peer.id} (${peer.type})`;
      if (peer.description) label.title = peer.description;
      const detach = document.createElement("button");
      detach.type = "button";
      detach.textContent = "Detach";
      detach.className = "quiet";
      detach.addEventListener("click", () =>
        this.act(
          "DELETE",
          role === "master"
            ? `/api/robots/${this.robotId}/master`
            : `/api/robots/${this.robotId}/slaves/${encodeURIComponent(peer.id)}`,
        ),
      );
      item.append(label, tag);
      if (peer.link) item.append(linkTag(peer.link));
      item.append(detach);
      // Its faults that last (each until it is over, a reset, or the peer leaves); a loss
      // while it lasts is its error without being one of them. The socket's `fault`
      // messages log each as it comes and goes.
      const troubles = (peer.faults || []).map((fault) => {
        const joint = fault.joint ? ` (${fault.joint})` : "";
        return { text: `${fault.code}${joint}: ${fault.message}`, severity: fault.severity };
      });
      if (!peer.connected && peer.last_error) troubles.unshift({ text: peer.last_error, severity: "error" });
      if (troubles.length) {
        const list = document.createElement("ul");
        list.className = "faults";
        for (const trouble of troubles) {
          const line = document.createElement("li");
          line.className = `fault ${trouble.severity}`;
          line.textContent = trouble.text;
          list.append(line);
        }
        item.append(list);
      }
      peers.append(item);
    }
    if (!entries.length) peers.innerHTML = '<li class="muted">nothing attached</li>';
    this.refreshSensors().catch((error) => this.log(`${error.code}: ${error.message}`, true));
  }

  /** The robot's cameras (live MJPEG streams beside the twin) and its episode. */
  async refreshSensors() {
    const base = `/api/robots/${encodeURIComponent(this.robotId)}`;
    const [{ cameras }, episodes] = await Promise.all([
      call("GET", `${base}/cameras`),
      call("GET", `${base}/episodes`),
    ]);
    if (this.closed) return;
    const box = $("cameras");
    const wanted = new Set(cameras.map((camera) => camera.name));
    for (const figure of [...box.children]) {
      if (!wanted.has(figure.dataset.camera)) figure.remove(); // its stream ends with it
    }
    for (const camera of cameras) {
      let figure = box.querySelector(`[data-camera="${CSS.escape(camera.name)}"]`);
      if (!figure) {
        figure = document.createElement("figure");
        figure.className = "camera";
        figure.dataset.camera = camera.name;
        const image = document.createElement("img");
        const key = apiKey();
        image.src = camera.stream + (key ? `?token=${encodeURIComponent(key)}` : "");
        image.alt = `camera ${camera.name}`;
        const caption = document.createElement("figcaption");
        const remove = document.createElement("button");
        remove.type = "button";
        remove.className = "quiet";
        remove.textContent = "Detach";
        remove.addEventListener("click", () =>
          this.act("DELETE", `${base}/cameras/${encodeURIComponent(camera.name)}`),
        );
        caption.append(document.createElement("span"), remove);
        figure.append(image, caption);
        box.append(figure);
      }
      const trouble = camera.error ? ` — ${camera.error}` : "";
      figure.querySelector("figcaption span").textContent =
        `${camera.name}: ${camera.width}×${camera.height} at ${camera.fps} fps, ` +
        `${camera.frames} frames${trouble}`;
      figure.classList.toggle("error", Boolean(camera.error));
    }
    const active = episodes.active;
    const status = $("episode-status");
    const counts = `${episodes.kept} kept, ${episodes.discarded} discarded`;
    status.textContent = active
      ? `episode ${active.index} recording, ${active.elapsed.toFixed(1)} s: ${active.task} (${counts})`
      : counts;
    status.className = active ? "episode-live" : "muted";
    status.dataset.episode = active ? String(active.index) : "";
    $("episode-start").disabled = Boolean(active);
    $("episode-stop").disabled = !active;
  }

  onMessage(type, data) {
    if (type === "state") this.applyState(data);
    else if (type === "joint_states") this.showJoints(data);
    else if (type === "fault") this.showFault(data);
  }

  /** A fault of a master, a slave or a camera as it comes or goes: logged, and the peers'
   * list fetched again so that it shows what lasts. */
  showFault(fault) {
    const joint = fault.joint ? ` (${fault.joint})` : "";
    if (fault.cleared) this.log(`${fault.peer_id}: ${fault.code}${joint} over: ${fault.message}`);
    else {
      const trouble = fault.severity === "error" || fault.severity === "critical";
      this.log(`${fault.peer_id}: ${fault.severity} ${fault.code}${joint}: ${fault.message}`, trouble);
    }
    // (at most one refresh a half second, however many faults come)
    if (!this.faultRefresh) {
      this.faultRefresh = setTimeout(() => {
        this.faultRefresh = null;
        if (!this.closed) this.onChanged();
      }, 500);
    }
  }

  /** The safety state: the badge, the master line, and whether the sliders may move. */
  applyState(state) {
    const previous = this.state;
    this.state = state;
    const badge = $("robot-state");
    badge.className = `state ${state.mode}`;
    badge.textContent = state.mode === "estopped" ? "E-STOPPED" : state.mode;
    badge.title = state.estop_reason || "";
    if (previous && previous.mode !== state.mode) {
      const why = state.mode === "estopped" ? `: ${state.estop_reason}` : "";
      this.log(`now ${state.mode}${why}`, state.mode === "estopped");
      this.onChanged();
    }
    if (previous && previous.mode === "intervened" && state.mode !== "intervened") {
      this.intervening = false; // handed back (or e-stopped): the sliders are not ours now
    }
    // The sliders drive an idle robot, or one this page intervenes on (as its operator).
    const locked = state.mode !== "idle" && !this.intervening;
    for (const { slider } of this.sliders.values()) slider.disabled = locked;
    $("master-pause").disabled = state.mode !== "mastered";
    $("master-resume").disabled = state.mode !== "paused";
    $("intervene").disabled = state.mode !== "mastered" && state.mode !== "paused";
    $("hand-back").disabled = state.mode !== "intervened";
    $("estop").disabled = state.mode === "estopped";
    $("reset").disabled = state.mode !== "estopped";
    showAttach(state.mode);
    this.showMaster();
  }

  /** The robot's master ({id, kind, description}) or null: as the newest pushed state says
   * (every change of master pushes one), else as the robot's details do. */
  master() {
    const pushed = this.state && this.state.master;
    return pushed !== undefined ? pushed : this.summary.master;
  }

  /** The master line: what plays or who holds the robot, in the server's words. */
  showMaster() {
    const state = this.state || {};
    const master = this.master();
    const kind = master ? master.kind || master.type : ""; // (`type`: a server of before kinds)
    let text;
    if (state.mode === "estopped") text = `E-stopped: ${state.estop_reason || "no reason given"}. Reset to move again.`;
    else if (state.mode === "intervened" && this.intervening) {
      text = "You intervene: the sliders drive the robot; the paused master waits for Hand back.";
    } else if (state.mode === "intervened" && master) {
      text = `Corrected by ${masterText(master)}: the paused master waits for the hand-back.`;
    } else if (state.mode === "paused" && master) {
      text = `Paused: ${masterText(master)} waits; the robot holds. Resume to go on.`;
    } else if (master && PLAYERS.has(kind)) {
      text = `Playing ${masterText(master)}: the sliders are locked.`;
    } else if (master) text = `Held by ${masterText(master)}: the sliders are locked.`;
    else if (state.owner) text = `Held by master '${state.owner}': the sliders are locked.`;
    else text = "No master: the sliders drive the robot.";
    $("master-line").textContent = text;
  }

  showJoints(joints) {
    this.lastJoints = joints;
    for (const joint of joints) {
      const entry = this.sliders.get(joint.name);
      if (!entry) continue;
      entry.virtual.textContent = degrees(joint.virtual_value);
      entry.real.textContent = degrees(joint.real_value);
      if (!entry.slider.dataset.held && !this.pending.has(joint.name) && !this.sending) {
        entry.slider.value = joint.virtual_value;
      }
    }
    if (this.twin) this.twin.show(joints);
    this.showLegend();
  }

  /** The legend's measured entry: whether there is a ghost, and why not. */
  showLegend() {
    const measured = (this.lastJoints || []).some(
      (joint) => joint.real_value !== null && joint.real_value !== undefined,
    );
    let text = "measured (ghost outline)";
    if (!this.summary.slaves.length) text = "measured: no slave";
    else if (!measured) text = "measured: nothing yet";
    document.querySelector('#twin-legend [data-part="measured"] .text').textContent = text;
  }

  /** Put the sliders of `names` back on the robot's values: a refused move moved nothing,
   * and no state comes to say so (a slider left where it was dragged lied about the arm). */
  showRobotValues(names) {
    for (const name of names) {
      const entry = this.sliders.get(name);
      const joint = (this.lastJoints || []).find((known) => known.name === name);
      if (entry && joint && !entry.slider.dataset.held && !this.pending.has(name)) {
        entry.slider.value = joint.virtual_value;
      }
    }
  }

  /** A slider moved: send the newest values, one request at a time. */
  queue(joint, value) {
    this.pending.set(joint, value);
    if (!this.sending) this.flush();
  }

  async flush() {
    this.sending = true;
    while (this.pending.size && !this.closed) {
      const joints = [...this.pending].map(([name, value]) => ({ name, value }));
      this.pending.clear();
      const started = performance.now();
      try {
        const ack = await call("PUT", `/api/robots/${this.robotId}/joints`, { joints });
        if (ack && ack.status === "clamped") this.log(`clamped: ${ack.message}`);
      } catch (error) {
        this.log(`${error.code}: ${error.message}`, true);
        this.showRobotValues(joints.map((joint) => joint.name));
        if (error.code === "COLLISION" && this.twin) {
          this.twin.showHit(collidingParts(error.message));
        }
      }
      const wait = SEND_INTERVAL - (performance.now() - started);
      if (wait > 0) await new Promise((resolve) => setTimeout(resolve, wait));
    }
    this.sending = false;
  }

  /** Draw the collision guard's workspace (floor, keep-out boxes) in the twin. */
  async showWorkspace() {
    const workspace = await call("GET", `/api/robots/${this.robotId}/workspace`);
    if (this.twin && !this.closed) this.twin.showWorkspace(workspace);
  }

  /** Call the API for a button; errors go to the events list. */
  async act(method, path, body) {
    const answer = await callReporting((text, isError) => this.log(text, isError), method, path, body);
    if (answer !== null) this.onChanged();
    return answer;
  }

  log(text, isError = false) {
    const item = document.createElement("li");
    item.textContent = `${new Date().toLocaleTimeString()} ${text}`;
    if (isError) item.className = "error";
    const events = $("events");
    events.prepend(item);
    while (events.children.length > MAX_EVENTS) events.lastChild.remove();
  }
}
