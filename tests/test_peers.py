"""The actor's pure bookkeeping of its peers (`arena.robot.peers`) and its idle turn
(`arena.robot.idle`), with plain values as links; then, through a robot, that the master it
shows is always the owner its safety state names."""

from __future__ import annotations

import dataclasses
import math

import trio
import trio.testing
from trio.testing import MockClock

from arena.drivers.sequence_master import SequenceMaster
from arena.drivers.sequences import get_sequence
from arena.protocol.errors import Severity
from arena.robot.events import PeerChanged
from arena.robot.handle import Robot
from arena.robot.idle import IdleTurn
from arena.robot.mailbox import LatestMailbox
from arena.robot.manager import RobotManager
from arena.robot.model import LossPolicy, load_robot_model
from arena.robot.peers import MAX_FAULTS, MasterPeer, Peers, SlavePeer
from arena.robot.snapshot import FaultSnapshot, PeerSnapshot


def master(
    peer_id: str = "alice", timeout: float | None = None, seen: float = 0.0
) -> MasterPeer[str]:
    return MasterPeer(peer_id, "websocket", f"link of {peer_id}", timeout, seen)


def slave(peer_id: str = "arm", timeout: float | None = None, seen: float = 0.0) -> SlavePeer[str]:
    return SlavePeer(peer_id, "mock-slave", f"link of {peer_id}", timeout, seen)


def test_the_master_goes_when_the_safety_state_no_longer_names_it_owner() -> None:
    peers: Peers[str, str] = Peers()
    assert peers.settle(None) is None  # no master: nothing to let go
    alice = master("alice")
    peers.add(alice)
    assert peers.settle("alice") is None and peers.master is alice  # still the owner
    assert peers.settle(None) is alice  # ownership ended (released, lost, timed out)
    assert peers.master is None and not peers.holds(alice)
    peers.add(alice)
    assert peers.settle("bob") is alice and peers.master is None  # another owns the robot


def test_a_record_is_known_by_itself_not_by_its_id() -> None:
    # A slave that left and another under the same id: the first one's late news (its
    # driver's end) must neither count as attached nor remove the second.
    peers: Peers[str, str] = Peers()
    first, second = slave("arm"), slave("arm")
    peers.add(first)
    assert peers.remove(first) and not peers.remove(first)
    peers.add(second)
    assert not peers.holds(first) and peers.holds(second)
    assert not peers.remove(first)
    assert peers.slaves == {"arm": second}
    old_alice, new_alice = master("alice"), master("alice")
    peers.add(old_alice)
    peers.add(new_alice)  # taken over under the same id (the old one was let go)
    assert not peers.holds(old_alice) and not peers.remove(old_alice)
    assert peers.master is new_alice


def test_the_master_is_found_by_its_id_or_as_whichever_holds_the_robot() -> None:
    peers: Peers[str, str] = Peers()
    assert peers.master_named(None) is None
    alice = master("alice")
    peers.add(alice)
    assert peers.master_named(None) is alice
    assert peers.master_named("alice") is alice
    assert peers.master_named("bob") is None


def test_heartbeats_set_the_deadlines_and_the_late_are_timed_out() -> None:
    peers: Peers[str, str] = Peers()
    assert peers.next_deadline() == math.inf and peers.timed_out(1e9) == []
    quiet, arm, alice = slave("quiet"), slave("arm", 2.0, 10.0), master("alice", 1.0, 10.0)
    for peer in (quiet, arm, alice):
        peers.add(peer)
    assert peers.next_deadline() == 11.0  # the master's
    peers.touch("alice", 10.5)
    assert peers.next_deadline() == 11.5
    assert peers.timed_out(11.49) == []
    assert peers.timed_out(11.5) == [alice]  # due at its deadline, not after it
    assert peers.timed_out(12.0) == [arm, alice]  # slaves first, as the actor goes through them
    peers.touch("arm", 12.0)
    assert peers.timed_out(12.0) == [alice]
    peers.touch("alice", 20.0)
    assert peers.next_deadline() == 14.0  # the slave's, now the earliest


def test_a_heartbeat_under_an_id_both_have_is_the_masters() -> None:
    peers: Peers[str, str] = Peers()
    twin, same = master("x", 1.0), slave("x", 1.0)
    peers.add(twin)
    peers.add(same)
    peers.touch("x", 5.0)
    assert (twin.last_seen, same.last_seen) == (5.0, 0.0)
    peers.touch("nobody", 6.0)  # unknown: changes nothing
    assert (twin.last_seen, same.last_seen) == (5.0, 0.0)


def test_peers_without_an_id_get_one_of_their_own() -> None:
    peers: Peers[str, str] = Peers()
    ids = [peers.new_id("slave"), peers.new_id("master"), peers.new_id("slave")]
    assert ids == ["slave-1", "master-2", "slave-3"]


def test_a_peers_change_and_snapshot_say_what_it_is() -> None:
    program = MasterPeer("seq", "mock-sequence", None, None, 0.0, autonomous=True, description="d")
    attached = program.changed("arm", "attached", "", 1.0, 2.0)
    assert attached == PeerChanged(
        "arm", "master", "seq", "mock-sequence", "attached", "", 1.0, 2.0, True
    )
    # Only the attach says whether the master plays a program.
    assert program.changed("arm", "detached", "done", 3.0, 4.0).autonomous is False
    assert program.snapshot() == PeerSnapshot(
        "seq", "master", "mock-sequence", True, None, False, "d"
    )
    arm = slave("arm")
    told = arm.fault("r", "SERVO_OVERHEAT", "servo 3 at 70 C", Severity.CRITICAL, "Elbow", 0.5, 9.0)
    assert (told.peer_id, told.joint, told.cleared) == ("arm", "Elbow", False)
    arm.connected, arm.out_of_reach = False, "unplugged"
    assert arm.changed("r", "disconnected", "unplugged", 1.0, 2.0).role == "slave"
    # While out of reach, that is its error; back in reach, the fault shows again.
    overheat = FaultSnapshot("SERVO_OVERHEAT", "servo 3 at 70 C", "critical", "Elbow", 0.5)
    assert arm.snapshot(joining=True) == PeerSnapshot(
        "arm", "slave", "mock-slave", False, "SLAVE_LOST: unplugged", True, "", (overheat,)
    )
    arm.connected = True
    assert arm.snapshot().last_error == "SERVO_OVERHEAT: servo 3 at 70 C"
    # A peer's faults are bounded: the oldest goes; the newest is its error.
    for k in range(MAX_FAULTS + 5):
        arm.fault("r", "X", f"fault {k}", Severity.WARNING, str(k), 1.0 + k, 9.0)
    assert len(arm.snapshot().faults) == MAX_FAULTS
    assert arm.snapshot().last_error == f"X: fault {MAX_FAULTS + 4}"
    (ended,) = arm.faults_over("r", "over", 20.0, 9.0, [("X", str(MAX_FAULTS + 4)), ("X", "0")])
    assert (ended.joint, ended.cleared, ended.severity) == (str(MAX_FAULTS + 4), True, "info")
    assert len(arm.faults_over("r", "reset", 21.0, 9.0)) == MAX_FAULTS - 1  # "0" went first


async def test_the_idle_turn_is_taken_only_while_open_and_before_the_waiters_timer(
    autojump_clock: MockClock,
) -> None:
    turn = IdleTurn()
    assert turn.now() is None  # nobody waits
    with trio.move_on_after(10.0) as wait:
        turn.open(wait)
        start = trio.current_time()
        assert turn.now() == start
        turn.wake_at(start + 20.0)  # a tick a stream on time does not need: put off
        assert wait.deadline == start + 20.0
        turn.wake_at(start + 1.0)  # a motion started in the turn needs a tick sooner
        assert wait.deadline == start + 1.0
        autojump_clock.jump(1.0)
        assert turn.now() is None  # its timer is due: the waiter goes first
        turn.close()
        assert turn.now() is None
        await trio.sleep_forever()
    mailbox_turn = IdleTurn()
    mailbox_turn.open()  # a waiter without a timer
    assert mailbox_turn.is_open and mailbox_turn.now() is not None
    mailbox_turn.wake_at(0.0)  # no timer to move
    mailbox_turn.close()
    assert not mailbox_turn.is_open and mailbox_turn.now() is None


async def test_an_item_queued_for_a_reader_closes_its_turn_so_nothing_overtakes_it() -> None:
    # The reader's hand-off declines a target (a socket with no room): it is queued and the
    # reader woken. A newer target offered before the reader runs must not go straight
    # through: the reader would then write the older one after it.
    box: LatestMailbox[str, str] = LatestMailbox()
    handed: list[str] = []
    accept = False

    def deliver_now(item: str) -> bool:
        if accept:
            handed.append(item)
        return accept

    box.deliver_now = deliver_now
    taken: list[str] = []

    async def reader() -> None:
        taken.append(await box.get())

    async with trio.open_nursery() as nursery:
        nursery.start_soon(reader)
        await trio.testing.wait_all_tasks_blocked()
        assert box.turn.is_open  # waiting with nothing queued
        box.put_target("t1")  # declined: queued
        accept = True
        box.put_target("t2")  # the reader has not run yet: replaces t1 in the box
        box.put_notice("n1")  # queued behind, too
        assert handed == [] and not box.turn.is_open
    assert taken == ["n1"] and await box.get() == "t2"


# --- through a robot: the record and the safety state's owner never disagree ----------------


def owner_and_master(robot: Robot) -> tuple[str | None, str | None]:
    snapshot = robot.snapshot()
    return snapshot.owner, None if snapshot.master is None else snapshot.master.peer_id


async def test_the_master_shown_is_always_the_owner_the_safety_state_names(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    robot = await manager.create_robot("so-arm100", robot_id="owned")
    alice = await robot.connect_master("alice")
    assert owner_and_master(robot) == ("alice", "alice")
    bob = await robot.connect_master("bob", takeover=True)  # displaced by the table's effect
    assert owner_and_master(robot) == ("bob", "bob") and alice.detached.is_set()
    await robot.estop("test")  # a live master stays the owner
    assert owner_and_master(robot) == ("bob", "bob")
    await bob.lost("unplugged")  # ownership ends: the record goes with it
    assert owner_and_master(robot) == (None, None) and bob.detached.is_set()
    await robot.reset()
    again = await robot.connect_master("bob", heartbeat_timeout=1.0)
    assert owner_and_master(robot) == ("bob", "bob")
    await trio.sleep(2.0)  # silent past its heartbeat timeout
    assert owner_and_master(robot) == (None, None) and again.detached.is_set()
    await robot.reset()
    program = await robot.attach_master(SequenceMaster([get_sequence("gentle-wave")]))
    assert owner_and_master(robot) == (program, program)
    await robot.estop("test")  # ends a program: the table detaches it
    assert owner_and_master(robot) == (None, None)


async def test_a_lost_master_goes_under_the_hold_policy_too(
    autojump_clock: MockClock, manager: RobotManager
) -> None:
    hold = dataclasses.replace(load_robot_model("so-arm100").safety, loss_policy=LossPolicy.HOLD)
    robot = await manager.create_robot("so-arm100", robot_id="held", policy=hold)
    alice = await robot.connect_master("alice")
    await alice.lost("unplugged")
    assert owner_and_master(robot) == (None, None) and robot.snapshot().mode == "idle"
    await robot.connect_master("bob")  # nothing left of alice holds the robot
    assert owner_and_master(robot) == ("bob", "bob")
