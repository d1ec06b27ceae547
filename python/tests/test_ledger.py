"""The reconciliation of fragment ledgers (junction.ledger): each produced fragment in exactly
one class, checkpoints and resumes deciding what survived, and every inconsistency counted."""

import json

from junction import ledger


def start(resumed=None):
    return {"event": "learner_start", "pid": 1, "resumed_update": resumed, "resumed_version": resumed}


def register(actor_id, instance):
    return {"event": "register", "actor_id": actor_id, "instance": instance, "transport": "grpc"}


def accepted(actor_id, seq):
    return {"event": "accepted", "actor_id": actor_id, "seq": seq, "agent_steps": 10}


def trained(update, *fragments):
    return {"event": "trained", "update": update, "fragments": [list(f) for f in fragments]}


def checkpoint(update):
    return {"event": "checkpoint", "update": update, "version": update}


def actor(instance, produced, sent=(), connection=1, stopped=False, confirmed=None):
    events = [{"event": "actor_start", "instance": instance, "transport": "grpc", "name": instance, "pid": 2}]
    events += [{"event": "produced", "instance": instance, "seq": s, "agent_steps": 10} for s in produced]
    events += [{"event": "sent", "instance": instance, "seq": s, "connection": connection} for s in sent]
    if confirmed is not None:
        events.append({"event": "confirmed", "instance": instance, "connection": connection, "fragments": confirmed})
    if stopped:
        events.append({"event": "actor_stop", "instance": instance})
    return events


def test_every_class_is_told_apart_across_a_killed_and_resumed_learner():
    # Process 1 trains updates 1 and 2, checkpoints at 1, is killed holding fragment 4.
    # Process 2 resumes from update 1 (update 2 is lost), trains update 2 again on new data,
    # drops one stale fragment and rejects one, then stops cleanly after checkpointing 2.
    learner = [
        start(),
        register("actor-1", "a"),
        accepted("actor-1", 0),
        trained(1, ("actor-1", 0)),
        checkpoint(1),
        accepted("actor-1", 1),
        trained(2, ("actor-1", 1)),
        accepted("actor-1", 2),
        start(resumed=1),
        register("actor-1", "b"),  # ids restart with the process; the instance tells them apart
        register("actor-2", "a"),
        accepted("actor-1", 0),
        accepted("actor-2", 5),
        trained(2, ("actor-1", 0), ("actor-2", 5)),
        accepted("actor-2", 6),
        {"event": "dropped", "actor_id": "actor-2", "seq": 6, "reason": "stale"},
        {"event": "rejected", "actor_id": "actor-2", "seq": 7, "reason": "nan"},
        checkpoint(2),
        {"event": "learner_stop"},
    ]
    actors = (
        actor("a", produced=range(10), sent=[0, 1, 2, 3, 5, 6, 7], stopped=True)
        + actor("b", produced=[0, 1], sent=[0])  # killed: 1 never sent
    )
    summary = ledger.reconcile(learner, actors)
    assert summary["unexplained"] == 0, summary["problems"]
    assert summary["classes"] == {
        "trained": 3,  # a0 (update 1, kept), b0 and a5 (update 2 of process 2)
        "lost_with_learner": 2,  # a1 (update 2 of process 1, after its checkpoint), a2 (queued)
        "dropped:stale": 1,
        "rejected:nan": 1,
        "lost_in_transport": 1,  # a3: sent, never seen
        "unsent_at_stop": 3,  # a4, a8, a9: never sent, and a stopped by itself
        "lost_with_actor": 1,  # b1: never sent, and b was killed
    }
    assert summary["produced"] == 12
    assert summary["learner_processes"] == 2 and summary["learner_clean_stops"] == 1


def test_updates_are_durable_only_along_the_line_of_checkpoints_that_were_resumed():
    a = lambda update, *keys: [accepted("x", k) for k in keys] + [trained(update, *[("x", k) for k in keys])]  # noqa: E731
    learner = (
        [start(), register("x", "i")]
        + a(10, 0)
        + [checkpoint(10)]
        + a(20, 1)
        + [checkpoint(20)]
        + a(21, 2)
        # Process 2 resumed from 10 (checkpoint 20 did not load): 11-20 of process 1 are gone.
        + [start(resumed=10), register("x", "i")]
        + a(11, 3)
        + [checkpoint(11), start(resumed=11), register("x", "i")]
        + a(12, 4)
        + [checkpoint(12), {"event": "learner_stop"}]
    )
    assert ledger.durable_updates(ledger.parse_learner(learner).segments) == [10, 11, 12]
    summary = ledger.reconcile(learner, actor("i", produced=range(5), sent=range(5), stopped=True))
    assert summary["classes"] == {"trained": 3, "lost_with_learner": 2}
    assert summary["unexplained"] == 0


def test_what_does_not_add_up_is_unexplained_and_fails():
    learner = [
        start(),
        register("actor-1", "a"),
        accepted("actor-1", 0),  # never trained or dropped, yet the learner stopped cleanly
        accepted("actor-1", 1),
        accepted("actor-1", 1),  # accepted twice
        accepted("actor-1", 9),  # no actor produced it
        accepted("actor-7", 0),  # an id the learner never registered
        accepted("actor-1", 2),
        trained(1, ("actor-1", 2)),
        {"event": "dropped", "actor_id": "actor-1", "seq": 2, "reason": "shutdown"},  # and dropped
        checkpoint(1),
        {"event": "learner_stop"},
    ]
    # The stream's summary claims 2 accepted; the learner accepted 3 of those sent on it.
    summary = ledger.reconcile(learner, actor("a", produced=range(3), sent=range(3), stopped=True, confirmed=2))
    assert summary["unexplained"] == 6, summary["problems"]
    assert summary["classes"] == {"unexplained": 3}
    assert len(summary["problems"]) == 6


def test_undecodable_messages_balance_against_what_test_clients_saw_refused(tmp_path):
    learner = [start(), {"event": "rejected", "actor_id": None, "seq": None, "reason": "decode"}, {"event": "learner_stop"}]
    hostile = actor("h", produced=[]) + [
        {"event": "garbage", "instance": "h", "code": "INVALID_ARGUMENT"},
        {"event": "garbage", "instance": "h", "code": "UNAVAILABLE"},  # lost on the way
    ]
    assert ledger.reconcile(learner, hostile)["unexplained"] == 0
    hostile.append({"event": "garbage", "instance": "h", "code": "INVALID_ARGUMENT"})
    assert ledger.reconcile(learner, hostile)["unexplained"] == 1

    # The command: a table, or one JSON object; exit 1 on imbalance, 2 on a file that is no ledger.
    (tmp_path / "l.jsonl").write_text("\n".join(json.dumps(e) for e in learner) + "\n")
    (tmp_path / "a.jsonl").write_text("\n".join(json.dumps(e) for e in hostile) + "\n")
    assert ledger.main([str(tmp_path / "l.jsonl"), str(tmp_path / "a.jsonl"), "--json"]) == 1
    (tmp_path / "bad.jsonl").write_text("not json\n")
    assert ledger.main([str(tmp_path / "bad.jsonl"), str(tmp_path / "a.jsonl")]) == 2
