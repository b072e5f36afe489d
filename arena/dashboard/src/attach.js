// Attaching a master from the robot's card: a policy from the robot's tenant's policy folder
// (`GET .../policies`), or a leader arm on a servo bus (a `usb-master` of the robot's type;
// `actuated`: it takes torque, is first driven to the follower's pose, then goes limp). While
// a master runs, the leader arm corrects it instead, as an intervention: that master waits,
// paused, until Hand back.

import { call } from "./api.js";

const $ = (id) => document.getElementById(id);

/** Whether a master runs (or waits, paused) that a new one would correct. */
function running(mode) {
  return mode === "mastered" || mode === "paused";
}

/** Fill the policy list with the robot's tenant's policies. */
export async function showPolicies(robotId) {
  const select = $("policy");
  try {
    const path = `/api/robots/${encodeURIComponent(robotId)}/policies`;
    const { policies, truncated } = await call("GET", path);
    const label = (policy) => (policy.type ? `${policy.name} (${policy.type})` : policy.name);
    select.replaceChildren(...policies.map((policy) => new Option(label(policy), policy.name)));
    if (truncated) select.append(new Option("(more not listed: name fewer)", "", false, false));
    if (!policies.length) select.append(new Option("no policy in this tenant's folder", ""));
  } catch (error) {
    select.replaceChildren(new Option(`policies: ${error.code}`, ""));
  }
  $("attach-policy").disabled = !select.value;
}

/** The leader arm's button says what it will do in the robot's safety state. */
export function showAttach(mode) {
  $("attach-leader").textContent = running(mode) ? "Correct with the leader arm" : "Attach leader arm";
}

/** Wire the buttons: `robotPath()` is the selected robot's path, `mode()` its safety state,
 * `act(method, path, body)` calls the API for a click (null once an error is shown). */
export function wireAttach({ robotPath, mode, act }) {
  $("policy").addEventListener("change", () => ($("attach-policy").disabled = !$("policy").value));
  $("attach-policy").addEventListener("click", async () => {
    const name = $("policy").value;
    if (!name) return;
    const body = { type: "policy", path: name };
    const task = $("policy-task").value.trim();
    if (task) body.task = task;
    const button = $("attach-policy");
    button.disabled = true; // loading takes seconds: one click, one policy
    $("attach-status").textContent = `loading ${name}…`;
    try {
      const answer = await act("POST", `${robotPath()}/master`, body);
      $("attach-status").textContent = answer ? `running ${answer.id}` : "";
    } finally {
      button.disabled = !$("policy").value;
    }
  });
  $("attach-leader").addEventListener("click", async () => {
    const master = { type: "usb-master", actuated: $("leader-actuated").checked };
    const port = $("leader-port").value.trim();
    if (port) master.port = port;
    const correct = running(mode());
    $("attach-status").textContent = "opening the leader arm…";
    const answer = correct
      ? await act("POST", `${robotPath()}/intervention`, { master })
      : await act("POST", `${robotPath()}/master`, master);
    $("attach-status").textContent = answer
      ? `leader arm ${correct ? "corrects" : "drives"} (${answer.intervening || answer.id})`
      : "";
  });
}
