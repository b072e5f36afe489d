"""`make mutants`: mutation testing of the modules whose failure hurts a person or an arm.

Runs mutmut (configured in pyproject.toml, `[tool.mutmut]`) one module at a time, smallest
first, one mutant at a time, each against only the tests that called the mutated function.
Then prints, per module, the mutants made, killed, survived and left as equivalent. The
equivalent mutants are the ones listed in specs/mutation.md with the reason each cannot be
told apart from the original; a listed mutant is matched by its function and the line it
changes (not by mutmut's number, which moves when the function changes), so an entry that no
longer matches any survivor is reported as stale.

    python tools/mutants.py                 # every module
    python tools/mutants.py safety motion   # some of them (names as in MODULES)
    python tools/mutants.py --report        # figures of the last runs, running nothing

Survivors are written, with their diffs, to mutants/survivors-<module>.txt.

Beside mutmut's mutants, `HAND_WRITTEN` lists mutants written by hand: changes mutmut never
makes (a bound scaled by a half, say) that a test is known to catch. Each runs after its module's
mutmut run, against the tests named for it, through the import hook of `tools/hand_mutation.py`
(the tree is never written to). tests/test_mutation_list.py checks that each one's text is still
in its file, so that the list cannot rot.
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SPEC = ROOT / "specs" / "mutation.md"

#: The modules under mutation, smallest first so that figures come early: the file, and the
#: functions whose mutants count (none listed: every function of the file). `Class.method` names
#: a method.
MODULES: dict[str, tuple[str, tuple[str, ...]]] = {
    "safety": ("arena/robot/safety.py", ()),
    "motion": ("arena/robot/motion.py", ()),
    "ramps": ("arena/robot/ramps.py", ()),
    "groups": ("arena/robot/groups.py", ()),
    "manager": ("arena/robot/manager.py", ()),
    "servo_arm": ("arena/drivers/servo_arm.py", ()),
    "usb_slave": (
        "arena/drivers/usb_slave.py",
        ("UsbSlave._follow", "UsbSlave._on_notice", "UsbSlave._hold", "UsbSlave._safe_job"),
    ),
    "worker": (
        "arena/servo/worker.py",
        (
            "BusWorker.stop",
            "BusWorker.clear_goals",
            "BusWorker._lose",
            "BusWorker._shutdown",
            "read_positions",
            "set_torque",
            "hold_here",
        ),
    ),
    "fleet_node": ("arena/fleet/node.py", ("FleetNode.ask", "FleetNode.ask_all")),
    "links": ("arena/robot/links.py", ()),
    "core": ("arena/robot/core.py", ()),
    "collision": ("arena/robot/collision.py", ()),
    "workspace": ("arena/robot/workspace.py", ()),
    "peers": ("arena/robot/peers.py", ()),
}


@dataclass(frozen=True)
class HandMutant:
    """A mutant written by hand: in `file` (of module `module`), the text `original`, which
    must occur exactly once, becomes `mutated`; `tests` (pytest node ids) are expected to
    fail. `why`: what the change would let through."""

    module: str
    file: str
    original: str
    mutated: str
    tests: tuple[str, ...]
    why: str


HAND_WRITTEN: tuple[HandMutant, ...] = (
    HandMutant(
        "collision",
        "arena/robot/collision.py",
        "total += sweep * units[k]",
        "total += sweep * units[k] * 0.5",
        (
            "tests/test_collision.py::"
            "test_the_shortcut_takes_the_whole_bound_a_turn_toward_a_box_is_checked_in_full",
        ),
        "the shortcut's bound half as tight: a move near a box or the arm's own links skips "
        "the full check that would refuse it",
    ),
    HandMutant(
        "collision",
        "arena/robot/collision.py",
        "floor_total += sweep * floor_units[k]",
        "floor_total += sweep * floor_units[k] * 0.5",
        ("tests/test_collision.py::test_small_steps_toward_the_table_never_get_a_target_into_it",),
        "the shortcut's floor bound half as tight: small steps toward the table get a target "
        "into it unchecked",
    ),
    HandMutant(
        "motion",
        "arena/robot/motion.py",
        "speeds[k] = goal.speed",
        "speeds[k] = goal.speed * 1.1",
        (
            "tests/test_motion_trajectory.py::"
            "test_a_step_command_keeps_the_limits_and_arrives_near_the_optimal_time",
        ),
        "every joint 10 % over its velocity limit",
    ),
    HandMutant(
        "ramps",
        "arena/robot/ramps.py",
        "min(self._speeds[name], stop)",
        "min(self._speeds[name] * 1.5, stop)",
        (
            "tests/test_joining.py::"
            "test_an_arm_joining_a_mastered_robot_is_brought_to_its_pose_at_the_joining_speed",
        ),
        "a joining arm brought to the robot's pose half again as fast as the joining speed",
    ),
    HandMutant(
        "ramps",
        "arena/robot/ramps.py",
        "change = accel * elapsed",
        "change = accel * elapsed * 1.5",
        (
            "tests/test_motion.py::"
            "test_a_join_starts_from_rest_and_lands_within_the_acceleration_limit",
        ),
        "a joining arm's velocity changed half again as fast as the acceleration limit",
    ),
)


def run_hand_written(mutant: HandMutant) -> str:
    """Run `mutant`'s tests against it: "killed" (a test failed), "survived" (all passed) or
    "broken: ..." (its text is not in the file once, no test imported the file, or pytest
    stopped for another reason)."""
    path = ROOT / mutant.file
    count = path.read_text(encoding="utf-8").count(mutant.original)
    if count != 1:
        return f"broken: {mutant.original!r} occurs {count} times in {mutant.file}"
    entry = {"file": str(path), "original": mutant.original, "mutated": mutant.mutated}
    env = {
        **os.environ,
        "ARENA_HAND_MUTANT": json.dumps(entry),
        "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tools")]),
    }
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-x", "-p", "hand_mutation", *mutant.tests],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode == 1:
        return "killed"
    if done.returncode == 0:
        return "survived"
    tail = (done.stdout + done.stderr).strip().splitlines()[-3:]
    return f"broken: pytest exit code {done.returncode}: {' / '.join(tail)}"


def hand_written_report(names: list[str]) -> int:
    """Run the hand-written mutants of the modules `names` and print each one's result; the
    number of them not killed."""
    chosen = [m for m in HAND_WRITTEN if m.module in names]
    if not chosen:
        return 0
    print("\nHand-written mutants (tools/mutants.py, HAND_WRITTEN):")
    missed = 0
    for mutant in chosen:
        result = run_hand_written(mutant)
        missed += result != "killed"
        print(f"  {mutant.module:<10} {result:<9} {mutant.original!r} -> {mutant.mutated!r}")
        if result != "killed":
            print(f"    ({mutant.why}; expected to be killed by {', '.join(mutant.tests)})")
    return missed


def patterns(module: str, suffix: str = "*") -> list[str]:
    """mutmut's names for the mutants of one module (globs). `mutmut run` is given them with a
    bare `*` (it matches them against function names too, to choose the clean tests), the
    figures with `__mutmut_*` (the mutants of exactly these functions)."""
    path, functions = MODULES[module]
    dotted = path.removesuffix(".py").replace("/", ".")
    if not functions:
        return [f"{dotted}.*"]
    return [f"{dotted}.x{_mangle(f)}{suffix}" for f in functions]


def _mangle(function: str) -> str:
    """`f` -> `_f`; `Class.method` -> `\u01c1Class\u01c1method` (mutmut's names for them)."""
    if "." in function:
        cls, method = function.split(".")
        return f"\u01c1{cls}\u01c1{method}"
    return f"_{function}"


KILLED = {1, 3}  # a test failed (3: pytest's internal error, which mutmut counts as a kill)
TIMEOUT = {36, -24, 24, 152, 255}  # the tests hung: the mutant is caught, by the time limit
SURVIVED = {0}
NO_TESTS = {5, 33}  # no selected test calls the function: a survivor by another name


@dataclass
class Figures:
    """What the last run of one module found."""

    made: int = 0
    killed: int = 0
    timeout: int = 0
    equivalent: int = 0
    survived: list[str] = field(default_factory=list)
    not_run: int = 0
    #: Survivors that no selected test calls: a test file missing from `[tool.mutmut]`.
    untested: int = 0

    @property
    def score(self) -> float:
        """Killed (timeouts included) or shown equivalent, as a share of all mutants made."""
        if not self.made:
            return 0.0
        return (self.killed + self.timeout + self.equivalent) / self.made


def equivalents() -> set[tuple[str, str, str]]:
    """(function, original line, mutated line) of every mutant specs/mutation.md calls equivalent.

    The table's rows look like ``| safety | `_rule` | `a < b` | `a <= b` | why |``. The mutant
    may be ``*`` (every mutant of that line) or ``(case)`` (a mutant that changes only the
    letter case of that line).
    """
    found: set[tuple[str, str, str]] = set()
    cell = re.compile(r"(?<!\\)\|")
    for line in SPEC.read_text(encoding="utf-8").splitlines():
        if not line.startswith("| ") or "`" not in line:
            continue
        cells = [c.strip().replace("\\|", "|") for c in cell.split(line)[1:-1]]
        if len(cells) < 5 or cells[0] not in MODULES:
            continue
        function, original, mutated = (c.strip("`") for c in cells[1:4])
        found.add((function, _squash(original), _squash(mutated)))
    return found


def matching(key: tuple[str, str, str], known: set[tuple[str, str, str]]) -> tuple[str, str, str]:
    """The entry of `known` that covers the survivor `key`, or `key` itself if it is not known."""
    function, original, mutated = key
    for entry in (key, (function, original, "*"), (function, original, "(case)")):
        if entry not in known:
            continue
        if entry[2] == "(case)" and mutated.lower() != original.lower():
            continue
        return entry
    return key


def _squash(code: str) -> str:
    return " ".join(code.split())


def function_of(mutant: str) -> str:
    """`arena.robot.safety.x_transition__mutmut_3` -> `transition`; methods -> `Class.method`."""
    name = mutant.rsplit(".", 1)[-1].rsplit("__mutmut_", 1)[0]
    name = name.removeprefix("x_").removeprefix("x\u01c1")
    return name.replace("\u01c1", ".")


def changed_lines(mutant: str) -> tuple[str, str]:
    """The original and the mutated lines of one mutant, each squashed to one line."""
    out = subprocess.run(
        [_mutmut(), "show", mutant], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout
    lines = out.splitlines()
    minus = [ln[1:] for ln in lines if ln.startswith("-") and not ln.startswith("---")]
    plus = [ln[1:] for ln in lines if ln.startswith("+") and not ln.startswith("+++")]
    return _squash(" ".join(minus)), _squash(" ".join(plus))


def _mutmut() -> str:
    return str(Path(sys.executable).parent / "mutmut")


def survivors(module: str) -> list[str]:
    """The mutants of one module that no test killed in its last run (timeouts too: a loaded
    machine can make a slow test look hung)."""
    meta = ROOT / "mutants" / (MODULES[module][0] + ".meta")
    if not meta.exists():
        return []
    codes: dict[str, int | None] = json.loads(meta.read_text())["exit_code_by_key"]
    wanted = patterns(module, "__mutmut_*")
    return sorted(
        m
        for m, code in codes.items()
        if code in SURVIVED | NO_TESTS | TIMEOUT and any(fnmatch.fnmatchcase(m, p) for p in wanted)
    )


def pending(module: str) -> list[str] | None:
    """The mutants of one module not yet tested, or None when all of them must be (no results
    yet, or the file changed since). mutmut tests again every mutant it is given by name or
    pattern, so a run that goes on after a stop names only these."""
    path, _ = MODULES[module]
    meta = ROOT / "mutants" / (path + ".meta")
    if not meta.exists() or (ROOT / path).stat().st_mtime > meta.stat().st_mtime:
        return None
    codes: dict[str, int | None] = json.loads(meta.read_text())["exit_code_by_key"]
    wanted = patterns(module, "__mutmut_*")
    return sorted(
        m
        for m, code in codes.items()
        if code is None and any(fnmatch.fnmatchcase(m, p) for p in wanted)
    )


def run(module: str, names: list[str] | None = None) -> None:
    """Mutate one module and test its mutants (or only `names`), one at a time. mutmut keeps
    a result until the function changes, so new tests reach old survivors only when these
    are named again (`--retest`)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    names = names or patterns(module)
    print(f"== {module}: mutmut run {' '.join(names) if len(names) < 4 else '...'}", flush=True)
    log = ROOT / "mutants" / f"run-{module}.log"
    log.parent.mkdir(exist_ok=True)
    with log.open("w") as out:
        done = subprocess.run(
            [_mutmut(), "run", "--max-children", "1", *names],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            check=False,
        )
    if done.returncode != 0:
        tail = log.read_text(errors="replace")[-2000:]
        print(f"mutmut stopped with exit code {done.returncode}; the end of {log}:\n{tail}")


def figures(
    module: str, known: set[tuple[str, str, str]], used: set[tuple[str, str, str]]
) -> Figures:
    """Count the last results of one module and write its survivors down."""
    meta = ROOT / "mutants" / (MODULES[module][0] + ".meta")
    result = Figures()
    if not meta.exists():
        return result
    codes: dict[str, int | None] = json.loads(meta.read_text())["exit_code_by_key"]
    report: list[str] = []
    wanted = patterns(module, "__mutmut_*")
    for mutant, code in sorted(codes.items()):
        if not any(fnmatch.fnmatchcase(mutant, p) for p in wanted):
            continue
        result.made += 1
        if code in KILLED:
            result.killed += 1
        elif code is None:
            result.not_run += 1
        else:
            original, mutated = changed_lines(mutant)
            entry = matching((function_of(mutant), original, mutated), known)
            if entry in known:  # shown equivalent, whatever a (timed out) run said
                result.equivalent += 1
                used.add(entry)
                continue
            if code in TIMEOUT:
                result.timeout += 1
                continue
            result.survived.append(mutant)
            result.untested += int(code in NO_TESTS)
            why = "no test calls it" if code in NO_TESTS else f"exit code {code}"
            report.append(f"{mutant} ({why})\n  - {original}\n  + {mutated}\n")
    (ROOT / "mutants" / f"survivors-{module}.txt").write_text("\n".join(report))
    return result


def main(argv: list[str]) -> int:
    """Run the modules asked (all by default), then print the figures of every module run."""
    report_only = "--report" in argv
    retest = "--retest" in argv
    names = [a for a in argv if not a.startswith("--")] or list(MODULES)
    unknown = [n for n in names if n not in MODULES]
    if unknown:
        print(f"unknown module(s) {unknown}; known: {', '.join(MODULES)}", file=sys.stderr)
        return 2
    if not report_only:
        for name in names:
            if retest:
                if again := survivors(name):
                    run(name, again)
            elif (left := pending(name)) is None:
                run(name)
            elif left:
                run(name, left)
    known = equivalents()
    used: set[tuple[str, str, str]] = set()
    print(
        f"{'module':<11} {'made':>5} {'killed':>6} {'timeout':>7} {'equiv':>5} {'survived':>8}"
        f" {'not run':>7} {'score':>6}"
    )
    untested: list[str] = []
    for name in names:
        f = figures(name, known, used)
        print(
            f"{name:<11} {f.made:>5} {f.killed:>6} {f.timeout:>7} {f.equivalent:>5}"
            f" {len(f.survived):>8} {f.not_run:>7} {f.score:>6.1%}"
        )
        if f.untested:
            untested.append(f"{name} ({f.untested})")
    if untested:
        print(
            f"\nSurvivors that no selected test calls: {', '.join(untested)}. The tests that"
            " reach them are not in [tool.mutmut]'s pytest_add_cli_args_test_selection (a"
            " change there makes mutmut test every mutant again)."
        )
    stale = {k for k in known if k[0] and k not in used}
    if stale and not report_only and names == list(MODULES):
        print("\nEquivalent entries in specs/mutation.md that match no survivor (stale):")
        for function, original, mutated in sorted(stale):
            print(f"  {function}: {original!r} -> {mutated!r}")
    print("\nSurvivors and their diffs: mutants/survivors-<module>.txt")
    if not report_only:
        hand_written_report(names)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
