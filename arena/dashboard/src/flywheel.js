// The card's lines for correcting a running master (the flywheel): who drives and who waits
// (`master`, `paused_master`), the policy's live figures, and the corrections (interventions)
// counted in the running episode and in all, as the robot's details give them.

import { masterText } from "./robot_view.js";

const $ = (id) => document.getElementById(id);

/** A policy's figures in words: its last inference, its last chunk, its stalls. */
export function policyFigures(figures) {
  const latency = `${Math.round((figures.last_latency || 0) * 1000)} ms`;
  return (
    `policy: inference ${latency}, chunk ${figures.last_chunk ?? "?"}, ` +
    `${figures.stalls} stall${figures.stalls === 1 ? "" : "s"}, ${figures.inferences} inferences`
  );
}

/** The corrections: in the running episode (if one runs) and in all. */
export function correctionsText(corrections) {
  const plural = (n) => `${n} correction${n === 1 ? "" : "s"}`;
  if (!corrections) return "";
  if (corrections.episode === null) return `${plural(corrections.total)} in all (no episode running)`;
  return `${plural(corrections.episode)} in this episode (${corrections.total} in all)`;
}

/** Show a robot's details (`GET /api/robots/{id}`) on the card. */
export function showFlywheel(summary) {
  const driving = summary.master;
  const waiting = summary.paused_master;
  $("who-drives").textContent = driving
    ? `drives: ${masterText(driving)}` + (waiting ? `; waits: ${masterText(waiting)}` : "")
    : "";
  const policy = [driving, waiting].find((master) => master && master.kind === "policy" && master.figures);
  const figures = $("policy-figures");
  figures.hidden = !policy;
  figures.textContent = policy ? policyFigures(policy.figures) : "";
  $("corrections").textContent = correctionsText(summary.corrections);
}
