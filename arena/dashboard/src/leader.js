// A simulated leader arm, moved from the page (`arena serve --sim-leader`, `make run`). The
// server owns the arm: `GET .../leader` names its port (offered in the leader's port field)
// and says whether the robot's leader arm is one of those; then these sliders move the
// leader's joints (`PUT .../leader/joints`) as a hand moves a real leader, and its usb-master
// drives the robot from what it reads, through every rule. They are the leader's, not the
// robot's: the robot's own sliders stay locked while the leader drives.

import { call } from "./api.js";

const $ = (id) => document.getElementById(id);

// A hand's moves go out at most this often (ms), the newest wins; each is a smooth move of
// this long (ms), so the leader glides between them. Well under the server's 50 a second.
const SEND_INTERVAL = 60;
const GLIDE_MS = 120;

export class LeaderPanel {
  constructor(report) {
    this.report = report;
    this.robotId = null;
    this.leaderId = null; // the simulated leader the sliders are built for
    this.sliders = new Map(); // joint -> { slider, reads }
    this.pending = new Map(); // joint -> value not yet sent
    this.sending = false;
    this.asked = 0; // counts questions: an older answer that comes late changes nothing
    this.offered = false; // the simulated leaders were offered for this robot
  }

  /** Ask where the robot's leader is (polled with the rest of the card, from the robot's
   * details `summary`): once for a robot just opened (the simulated leaders to offer), then
   * only while a leader arm drives it or waits on it. */
  async refresh(robotId, summary) {
    if (robotId !== this.robotId) this.close();
    this.robotId = robotId;
    const isLeader = (peer) => Boolean(peer) && (peer.kind || peer.type) === "usb-master";
    if (this.offered && !isLeader(summary.master) && !isLeader(summary.paused_master)) {
      $("sim-leader").hidden = true;
      this.leaderId = null;
      return;
    }
    const robotType = summary.robot_type;
    const mine = ++this.asked;
    let shown;
    try {
      shown = await call("GET", `/api/robots/${encodeURIComponent(robotId)}/leader`);
    } catch {
      return; // (an older server, or a moment's error: the next refresh asks again)
    }
    if (mine !== this.asked || robotId !== this.robotId) return;
    this.offered = true;
    this.offerPorts(shown.simulated, robotType);
    const leader = shown.leader && shown.leader.simulated ? shown.leader : null;
    $("sim-leader").hidden = !leader;
    if (!leader) {
      this.leaderId = null;
      return;
    }
    if (leader.id !== this.leaderId) this.build(leader);
    for (const joint of leader.joints) {
      const entry = this.sliders.get(joint.name);
      if (!entry || joint.value === null) continue;
      entry.reads.textContent = joint.value.toFixed(1);
      if (!entry.slider.dataset.held && !this.pending.has(joint.name)) entry.slider.value = joint.value;
    }
    $("sim-leader-note").textContent = leader.driving
      ? `Your hand on the simulated leader (${leader.id}): it drives the robot.`
      : `Your hand on the simulated leader (${leader.id}): it waits while another intervenes.`;
  }

  /** The server's simulated leaders as choices for the leader's port; the field filled with
   * one of the robot's type while it is empty and nobody is typing in it. */
  offerPorts(simulated, robotType) {
    const list = $("sim-leader-ports");
    list.replaceChildren(...simulated.map((sim) => new Option(`simulated ${sim.robot_type} leader`, sim.port)));
    const field = $("leader-port");
    const fitting = simulated.find((sim) => sim.robot_type === robotType) || simulated[0];
    if (fitting && !field.value && document.activeElement !== field && !field.dataset.offered) {
      field.value = fitting.port;
      field.dataset.offered = "1"; // once: a field emptied by the user stays empty
    }
  }

  build(leader) {
    this.leaderId = leader.id;
    this.sliders.clear();
    this.pending.clear();
    const body = $("leader-joints").querySelector("tbody");
    body.replaceChildren();
    for (const joint of leader.joints) {
      const slider = document.createElement("input");
      slider.type = "range";
      slider.min = joint.min;
      slider.max = joint.max;
      slider.step = 0.5;
      slider.value = joint.value ?? 0;
      slider.dataset.leaderJoint = joint.name;
      slider.setAttribute("aria-label", `leader ${joint.name}`);
      slider.title = `${joint.min.toFixed(0)} to ${joint.max.toFixed(0)} ${joint.unit === "%" ? "%" : "°"}`;
      slider.addEventListener("input", () => this.queue(joint.name, Number(slider.value)));
      slider.addEventListener("pointerdown", () => (slider.dataset.held = "1"));
      slider.addEventListener("pointerup", () => delete slider.dataset.held);
      slider.addEventListener("blur", () => delete slider.dataset.held);
      const row = document.createElement("tr");
      const reads = document.createElement("td");
      reads.className = "value";
      const name = document.createElement("td");
      name.textContent = `${joint.name} (${joint.unit === "%" ? "%" : "°"})`;
      const cell = document.createElement("td");
      cell.append(slider);
      row.append(name, cell, reads);
      body.append(row);
      this.sliders.set(joint.name, { slider, reads });
    }
  }

  queue(joint, value) {
    this.pending.set(joint, value);
    if (!this.sending) this.flush();
  }

  async flush() {
    this.sending = true;
    const robotId = this.robotId;
    while (this.pending.size && robotId === this.robotId) {
      const joints = [...this.pending].map(([name, value]) => ({ name, value }));
      this.pending.clear();
      const path = `/api/robots/${encodeURIComponent(robotId)}/leader/joints`;
      try {
        await call("PUT", path, { joints, duration: GLIDE_MS });
        $("sim-leader-status").textContent = "";
      } catch (error) {
        $("sim-leader-status").textContent = `${error.code}: ${error.message}`;
        if (error.code !== "RATE_LIMITED") this.report(`leader: ${error.code}: ${error.message}`, true);
      }
      await new Promise((resolve) => setTimeout(resolve, SEND_INTERVAL));
    }
    this.sending = false;
  }

  close() {
    this.robotId = null;
    this.offered = false;
    this.leaderId = null;
    this.sliders.clear();
    this.pending.clear();
    $("leader-joints").querySelector("tbody").replaceChildren();
    $("sim-leader").hidden = true;
    const field = $("leader-port");
    if (field.dataset.offered) {
      delete field.dataset.offered;
      field.value = "";
    }
  }
}
