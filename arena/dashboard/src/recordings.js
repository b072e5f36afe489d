// The recordings panel: the recorder's state, start and stop, the files with download,
// replay onto the selected robot, and a plot of a recording's joints (in a dialog over the
// page, as wide as the screen allows, with labelled axes).

import { call, callReporting, download } from "./api.js";

const $ = (id) => document.getElementById(id);
const COLORS = ["#e8a33d", "#3d8be8", "#46c37b", "#e5484d", "#b07be8", "#3dd6e8", "#e87bd0"];
const FONT_PX = 13; // the plot's labels, as large as the page's small text

function size(bytes) {
  return bytes > 1e6 ? `${(bytes / 1e6).toFixed(1)} MB` : `${Math.ceil(bytes / 1e3)} kB`;
}

export class RecordingsPanel {
  /** `selectedRobot()` names the robot a replay goes to; `report(text, isError)` logs; a
   * replay onto a robot with a master takes over on a second click (`takeover`, a
   * SecondClickTakeover; `holder()` says who holds the selected robot). */
  constructor({ selectedRobot, report, takeover, holder }) {
    this.selectedRobot = selectedRobot;
    this.report = report;
    this.takeover = takeover;
    this.holder = holder;
    $("record-start").addEventListener("click", () => this.act("POST", "/api/recordings"));
    $("record-stop").addEventListener("click", () =>
      this.act("POST", "/api/recordings/current/stop"),
    );
    this.series = null; // what the plot shows, drawn again when its size changes
    document.addEventListener("keydown", (event) => {
      if (event.key === "Escape" && $("plot-dialog").open) $("plot-dialog").close();
    });
    new ResizeObserver(() => {
      if (this.series && $("plot-dialog").open) drawSeries($("plot"), this.series);
    }).observe($("plot"));
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
        this.replayButton(file.name),
        this.button("Plot", () => this.plot(file.name)),
      );
      list.append(item);
    }
    if (!listing.recordings.length) list.innerHTML = '<li class="muted">no recordings yet</li>';
    this.showArmed();
  }

  replayButton(name) {
    const button = this.button("Replay", () => this.replay(name));
    button.dataset.replay = name;
    return button;
  }

  /** Label each Replay button: the one refused a moment ago offers to take over. */
  showArmed() {
    for (const button of document.querySelectorAll("#recording-list button[data-replay]")) {
      const armed = this.takeover.isArmed(this.replayKey(button.dataset.replay));
      button.textContent = armed ? "Take over with this replay?" : "Replay";
      button.classList.toggle("armed", armed);
    }
  }

  replayKey(name) {
    return JSON.stringify([this.selectedRobot(), name]);
  }

  button(text, onClick) {
    const button = document.createElement("button");
    button.type = "button";
    button.className = "quiet";
    button.textContent = text;
    button.addEventListener("click", onClick);
    return button;
  }

  /** Replay `name` onto the selected robot; over a master only on a second click. */
  async replay(name) {
    const robot = this.selectedRobot();
    if (!robot) {
      this.report("Choose a robot to replay onto first.", true);
      return;
    }
    const key = this.replayKey(name);
    const answer = await this.takeover.request(
      key,
      (takeover) =>
        call("POST", `/api/robots/${encodeURIComponent(robot)}/replay`, {
          recording: name,
          takeover,
        }),
      { report: this.report, holder: this.holder, stillWanted: () => this.replayKey(name) === key },
    );
    if (!answer) return;
    this.report(`replaying ${name} onto ${robot} as master ${answer.master}`);
    await this.refresh();
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
    $("plot-title").textContent = `${series.recording}: robot ${series.robot}`;
    const dialog = $("plot-dialog");
    // Not modal: E-STOP, STOP ALL and Reset must stay usable. Below the header, opened before
    // drawing so that the canvas has its shown size.
    dialog.style.top = `${document.querySelector("header").getBoundingClientRect().bottom + 8}px`;
    if (!dialog.open) dialog.show();
    const canvas = $("plot");
    this.series = series;
    drawSeries(canvas, series);
    canvas.dataset.recording = series.recording;
    canvas.dataset.points = String(
      series.joints.reduce((sum, joint) => sum + joint.virtual.length + joint.real.length, 0),
    );
    const legend = $("plot-legend");
    legend.replaceChildren(
      ...series.joints.map((joint, index) => legendEntry(joint.name, COLORS[index % COLORS.length])),
    );
    legend.append(
      `solid: virtual (commanded), dashed: real (measured)${series.estops.length ? ", red line: e-stop" : ""}`,
    );
  }
}

function legendEntry(text, color) {
  const entry = document.createElement("span");
  const swatch = document.createElement("span");
  swatch.className = "swatch";
  swatch.style.borderColor = swatch.style.background = color;
  entry.append(swatch, text);
  return entry;
}

/** About `count` round steps (1, 2 or 5 times a power of ten) from `low` to `high`. */
export function ticks(low, high, count) {
  const rough = (high - low) / count;
  const power = 10 ** Math.floor(Math.log10(rough));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= rough) || 10 * power;
  const first = Math.ceil(low / step - 1e-9) * step;
  const found = [];
  for (let at = first; at <= high + step * 1e-9; at += step) found.push(Number(at.toFixed(6)));
  return found;
}

/** Draw `series` on `canvas` at the size the canvas shows (CSS pixels, sharp on any screen). */
function drawSeries(canvas, series) {
  const shown = canvas.getBoundingClientRect();
  const ratio = window.devicePixelRatio || 1;
  canvas.width = Math.ceil(shown.width * ratio);
  canvas.height = Math.ceil(shown.height * ratio);
  const context = canvas.getContext("2d");
  context.setTransform(ratio, 0, 0, ratio, 0, 0);
  const width = shown.width;
  const height = shown.height;
  const left = 56; // room for the degree labels and the axis's name
  const right = 16;
  const top = 16;
  const bottom = 44; // room for the time labels and the axis's name
  context.clearRect(0, 0, width, height);
  context.font = `${FONT_PX}px system-ui, sans-serif`;
  const points = series.joints.flatMap((joint) => [...joint.virtual, ...joint.real]);
  if (!points.length) {
    context.fillStyle = "#9aa3b2";
    context.fillText("No joint data for this robot in the recording.", left, height / 2);
    canvas.dataset.ticks = "";
    return;
  }
  const times = points.map((p) => p[0]);
  const values = points.map((p) => p[1]);
  const t0 = Math.min(...times);
  const t1 = Math.max(...times, t0 + 1e-3);
  const v0 = Math.min(...values, -1);
  const v1 = Math.max(...values, 1);
  const x = (t) => left + ((t - t0) / (t1 - t0)) * (width - left - right);
  const y = (v) => height - bottom - ((v - v0) / (v1 - v0)) * (height - top - bottom);
  // Grid and labels: seconds from the recording's first point, degrees.
  const xTicks = ticks(0, t1 - t0, Math.max(4, Math.floor(width / 110)));
  const yTicks = ticks(v0, v1, Math.max(4, Math.floor(height / 60)));
  context.lineWidth = 1;
  context.strokeStyle = "#2a303b";
  context.fillStyle = "#9aa3b2";
  context.textAlign = "center";
  context.textBaseline = "top";
  for (const at of xTicks) {
    context.beginPath();
    context.moveTo(x(t0 + at), top);
    context.lineTo(x(t0 + at), height - bottom);
    context.stroke();
    context.fillText(`${at}`, x(t0 + at), height - bottom + 5);
  }
  context.fillText("time (s)", left + (width - left - right) / 2, height - FONT_PX - 6);
  context.textAlign = "right";
  context.textBaseline = "middle";
  for (const at of yTicks) {
    context.beginPath();
    context.moveTo(left, y(at));
    context.lineTo(width - right, y(at));
    context.stroke();
    context.fillText(`${at}°`, left - 6, y(at));
  }
  context.save();
  context.translate(14, top + (height - top - bottom) / 2);
  context.rotate(-Math.PI / 2);
  context.textAlign = "center";
  context.fillText("degrees", 0, 0);
  context.restore();
  context.strokeStyle = "#4a5262";
  context.strokeRect(left, top, width - left - right, height - top - bottom);
  canvas.dataset.ticks = `${xTicks.join(",")};${yTicks.join(",")}`;
  context.lineWidth = 1.5;
  context.strokeStyle = "#e5484d";
  for (const at of series.estops) {
    context.beginPath();
    context.moveTo(x(at), top);
    context.lineTo(x(at), height - bottom);
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
      // Steps: a joint is recorded when it changes, so each value holds until the next (a
      // straight line drew a slope over a still arm's minutes).
      line.forEach(([t, v], i) => {
        if (i === 0) context.moveTo(x(t), y(v));
        else context.lineTo(x(t), y(line[i - 1][1]));
        context.lineTo(x(t), y(v));
      });
      context.stroke();
    }
  });
  context.setLineDash([]);
}
