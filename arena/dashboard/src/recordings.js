// The recordings panel: the recorder's state, start and stop, the files with download,
// replay onto the selected robot, and a small plot of a recording's joints.

import { call, callReporting, download } from "./api.js";

const $ = (id) => document.getElementById(id);
const COLORS = ["#e8a33d", "#3d8be8", "#46c37b", "#e5484d", "#b07be8", "#3dd6e8", "#e87bd0"];
const COLOR_NAMES = ["orange", "blue", "green", "red", "violet", "cyan", "pink"];

function size(bytes) {
  return bytes > 1e6 ? `${(bytes / 1e6).toFixed(1)} MB` : `${Math.ceil(bytes / 1e3)} kB`;
}

export class RecordingsPanel {
  /** `selectedRobot()` names the robot a replay goes to; `report(text, isError)` logs. */
  constructor({ selectedRobot, report }) {
    this.selectedRobot = selectedRobot;
    this.report = report;
    $("record-start").addEventListener("click", () => this.act("POST", "/api/recordings"));
    $("record-stop").addEventListener("click", () =>
      this.act("POST", "/api/recordings/current/stop"),
    );
  }

  async act(method, path, body) {
    const answer = await callReporting(this.report, method, path, body);
    if (answer !== null) await this.refresh();
    return answer;
  }

  async refresh() {
    let listing;
    try {
      listing = await call("GET", "/api/recordings");
    } catch (error) {
      $("recorder-status").textContent = `${error.code}: ${error.message}`;
      return;
    }
    const recorder = listing.recorder;
    const status = $("recorder-status");
    status.classList.toggle("failing", Boolean(recorder.active && recorder.error));
    if (recorder.active && recorder.error) {
      // The disk refuses: control goes on, but nothing is being recorded. Say so plainly.
      const retry = recorder.retry_in ? `; retrying in ${Math.ceil(recorder.retry_in)} s` : "";
      status.textContent =
        `Recording stopped: ${recorder.error}${retry} (${recorder.dropped} messages lost).`;
    } else {
      status.textContent = recorder.active
        ? `Recording to ${recorder.file || "(next message starts a file)"}: ${recorder.messages} messages` +
          (recorder.dropped ? `, ${recorder.dropped} dropped` : "")
        : "Not recording.";
    }
    $("record-start").disabled = recorder.active;
    $("record-stop").disabled = !recorder.active;
    const list = $("recording-list");
    list.replaceChildren();
    for (const file of listing.recordings) {
      const item = document.createElement("li");
      item.dataset.recording = file.name;
      const label = document.createElement("span");
      label.textContent = `${file.name} (${size(file.bytes)})${file.active ? " ● recording" : ""}`;
      item.append(
        label,
        this.button("Download", () =>
          download(`/api/recordings/${encodeURIComponent(file.name)}/file`, file.name).catch(
            (error) => this.report(`${error.code}: ${error.message}`, true),
          ),
        ),
        this.button("Replay", () => this.replay(file.name)),
        this.button("Plot", () => this.plot(file.name)),
      );
      list.append(item);
    }
    if (!listing.recordings.length) list.innerHTML = '<li class="muted">no recordings yet</li>';
  }

  button(text, onClick) {
    const button = document.createElement("button");
    button.type = "button";
    button.className = "quiet";
    button.textContent = text;
    button.addEventListener("click", onClick);
    return button;
  }

  async replay(name) {
    const robot = this.selectedRobot();
    if (!robot) {
      this.report("Choose a robot to replay onto first.", true);
      return;
    }
    const answer = await this.act("POST", `/api/robots/${encodeURIComponent(robot)}/replay`, {
      recording: name,
    });
    if (answer) this.report(`replaying ${name} onto ${robot} as master ${answer.master}`);
  }

  /** Draw every joint of one robot of the recording: virtual solid, real dashed. */
  async plot(name) {
    const robot = this.selectedRobot();
    const query = new URLSearchParams({ points: "300" });
    if (robot) query.set("robot", robot);
    let series;
    try {
      series = await call("GET", `/api/recordings/${encodeURIComponent(name)}/joints?${query}`);
    } catch (error) {
      if (error.code !== "UNKNOWN_ROBOT" || !robot) {
        this.report(`${error.code}: ${error.message}`, true);
        return;
      }
      // The selected robot is not in this file: plot the first robot that is.
      query.delete("robot");
      const path = `/api/recordings/${encodeURIComponent(name)}/joints?${query}`;
      series = await callReporting(this.report, "GET", path);
      if (!series) return;
    }
    const canvas = $("plot");
    canvas.hidden = false;
    drawSeries(canvas, series);
    canvas.dataset.recording = series.recording;
    canvas.dataset.points = String(
      series.joints.reduce((sum, joint) => sum + joint.virtual.length + joint.real.length, 0),
    );
    $("plot-legend").textContent =
      `${series.recording}, robot ${series.robot} (solid: virtual, dashed: real` +
      `${series.estops.length ? ", red: e-stop" : ""}): ` +
      series.joints.map((joint, i) => `${joint.name} ${COLOR_NAMES[i % COLORS.length]}`).join(", ");
  }
}

function drawSeries(canvas, series) {
  const context = canvas.getContext("2d");
  const { width, height } = canvas;
  const pad = 28;
  context.clearRect(0, 0, width, height);
  const points = series.joints.flatMap((joint) => [...joint.virtual, ...joint.real]);
  if (!points.length) {
    context.fillStyle = "#9aa3b2";
    context.fillText("No joint data for this robot in the recording.", pad, height / 2);
    return;
  }
  const times = points.map((p) => p[0]);
  const values = points.map((p) => p[1]);
  const t0 = Math.min(...times);
  const t1 = Math.max(...times, t0 + 1e-3);
  const v0 = Math.min(...values, -1);
  const v1 = Math.max(...values, 1);
  const x = (t) => pad + ((t - t0) / (t1 - t0)) * (width - 2 * pad);
  const y = (v) => height - pad - ((v - v0) / (v1 - v0)) * (height - 2 * pad);
  context.strokeStyle = "#333a46";
  context.strokeRect(pad, pad, width - 2 * pad, height - 2 * pad);
  context.fillStyle = "#9aa3b2";
  context.font = "11px sans-serif";
  context.fillText(`${v1.toFixed(0)}°`, 2, pad + 4);
  context.fillText(`${v0.toFixed(0)}°`, 2, height - pad);
  context.fillText(`${(t1 - t0).toFixed(1)} s`, width - pad - 24, height - 8);
  context.strokeStyle = "#e5484d";
  for (const at of series.estops) {
    context.beginPath();
    context.moveTo(x(at), pad);
    context.lineTo(x(at), height - pad);
    context.stroke();
  }
  series.joints.forEach((joint, index) => {
    context.strokeStyle = COLORS[index % COLORS.length];
    for (const [line, dash] of [
      [joint.virtual, []],
      [joint.real, [4, 3]],
    ]) {
      if (!line.length) continue;
      context.setLineDash(dash);
      context.beginPath();
      line.forEach(([t, v], i) => (i ? context.lineTo(x(t), y(v)) : context.moveTo(x(t), y(v))));
      context.stroke();
    }
  });
  context.setLineDash([]);
}
