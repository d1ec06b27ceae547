"""Reconciles the fragment ledgers of a run: every fragment an actor produced, followed to its
end through every learner process that ran (docs/FAULTS.md, "Every fragment accounted for").

    python -m junction.ledger RUN_DIR/ledger.jsonl ACTOR_LEDGER... [--json]

The learner appends `RUN_DIR/ledger.jsonl` (one segment per learner process, each opened by a
`learner_start` line); each actor appends its own (`actor --ledger FILE`; local actors write
`RUN_DIR/ledger/local-i.jsonl`). Fragments are named by (actor instance, sequence number);
the learner names them by actor id, which its `register` lines map to instances within
one segment. Each produced fragment ends in exactly one class (``CLASSES``); what fits none
(a learner record of a fragment no actor produced, a fragment accepted twice, a stream whose
confirmed count disagrees with the learner, a fragment left untrained in a learner that
stopped cleanly) is counted as unexplained, and the exit status is 1.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

#: Where a produced fragment can end, in the order the table prints them.
CLASSES = (
    "trained",  # in an update that every later learner process kept (a checkpoint holds it)
    "lost_with_learner",  # accepted, then the learner died before a checkpoint covered it
    "dropped",  # accepted and not trained on, by reason (stale, shutdown, update_failed)
    "rejected",  # refused before the queue, by reason
    "refused_by_transport",  # refused by gRPC itself (too large) before the learner saw it
    "lost_in_transport",  # sent, never seen by the learner (a link, connection or learner died)
    "unsent_at_stop",  # produced, not sent when the actor stopped by itself
    "lost_with_actor",  # produced, not sent when the actor was killed
)


class LedgerError(ValueError):
    """A ledger file that is not a ledger (a usage error, not an imbalance)."""


def read_lines(path: Path) -> list[dict]:
    events = []
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                event = json.loads(line)
            except json.JSONDecodeError as e:
                raise LedgerError(f"{path}:{number}: not a JSON line ({e})") from None
            if not isinstance(event, dict) or "event" not in event:
                raise LedgerError(f"{path}:{number}: a JSON line without an 'event'")
            events.append(event)
    return events


@dataclass
class Segment:
    """One learner process: from its `learner_start` to the next (or the file's end)."""

    resumed_update: int | None
    ids: dict[str, str] = field(default_factory=dict)
    checkpoints: list[int] = field(default_factory=list)
    stopped: bool = False
    #: (instance, seq) -> [(kind, detail)] in the order written.
    records: dict[tuple[str, int], list[tuple[str, object]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    #: (instance, seq) -> update number, for fragments this process trained on.
    trained: dict[tuple[str, int], int] = field(default_factory=dict)


@dataclass
class LearnerLedger:
    segments: list[Segment]
    #: Records naming no actor this learner process registered (undecodable bytes, made-up
    #: ids): by kind and reason.
    unattributed: Counter


def parse_learner(events: list[dict], path: Path | str = "learner ledger") -> LearnerLedger:
    segments: list[Segment] = []
    unattributed: Counter = Counter()
    for event in events:
        kind = event["event"]
        if kind == "learner_start":
            segments.append(Segment(resumed_update=event.get("resumed_update")))
            continue
        if not segments:
            raise LedgerError(f"{path}: a {kind!r} line before the first learner_start")
        segment = segments[-1]
        if kind == "register":
            segment.ids[event["actor_id"]] = event["instance"]
        elif kind == "checkpoint":
            segment.checkpoints.append(int(event["update"]))
        elif kind == "learner_stop":
            segment.stopped = True
        elif kind == "trained":
            for actor_id, seq in event["fragments"]:
                key = _key(segment, actor_id, seq)
                if key is None:
                    unattributed["trained"] += 1
                    continue
                segment.records[key].append(("trained", int(event["update"])))
                segment.trained[key] = int(event["update"])
        elif kind in ("accepted", "rejected", "dropped"):
            key = _key(segment, event.get("actor_id"), event.get("seq"))
            detail = event.get("reason", event.get("agent_steps"))
            if key is None:
                unattributed[f"{kind}:{event.get('reason', '')}".rstrip(":")] += 1
            else:
                segment.records[key].append((kind, detail))
        else:
            raise LedgerError(f"{path}: unknown learner event {kind!r}")
    return LearnerLedger(segments, unattributed)


def _key(segment: Segment, actor_id, seq) -> tuple[str, int] | None:
    if actor_id is None or seq is None:
        return None
    instance = segment.ids.get(actor_id)
    if not instance:
        return None
    return (instance, int(seq))


def durable_updates(segments: list[Segment]) -> list[int]:
    """Per segment, the highest update of that process that survives in the final state
    (-1: none). The final state is the newest checkpoint; walking back, each process holds
    the updates up to the checkpoint the next one in the line resumed from."""
    durable = [-1] * len(segments)
    if not segments:
        return durable
    s = len(segments) - 1
    if segments[s].checkpoints:
        upto = max(segments[s].checkpoints)
    else:
        upto = segments[s].resumed_update
        s = _writer(segments, s, upto)
    while s is not None and upto is not None:
        durable[s] = max(durable[s], upto)
        upto = segments[s].resumed_update
        s = _writer(segments, s, upto)
    return durable


def _writer(segments: list[Segment], before: int, update: int | None) -> int | None:
    """The latest process before `before` that wrote a checkpoint of `update`."""
    if update is None:
        return None
    for k in range(before - 1, -1, -1):
        if update in segments[k].checkpoints:
            return k
    return None


@dataclass
class ActorInstance:
    name: str
    transport: str
    stopped: bool = False
    produced: dict[int, int] = field(default_factory=dict)  # seq -> agent-steps
    sent: dict[int, int] = field(default_factory=dict)  # seq -> connection
    refused: set[int] = field(default_factory=set)
    confirmed: list[tuple[int, int]] = field(default_factory=list)  # (connection, fragments)
    garbage: Counter = field(default_factory=Counter)  # reply code -> messages


def parse_actors(events: list[dict], path: Path | str = "actor ledger") -> dict[str, ActorInstance]:
    instances: dict[str, ActorInstance] = {}
    for event in events:
        kind = event["event"]
        instance_id = event.get("instance")
        if instance_id is None:
            raise LedgerError(f"{path}: a {kind!r} line without an instance")
        if kind == "actor_start":
            instances[instance_id] = ActorInstance(event.get("name", ""), event.get("transport", ""))
            continue
        instance = instances.get(instance_id)
        if instance is None:
            raise LedgerError(f"{path}: a {kind!r} line of {instance_id!r} before its actor_start")
        if kind == "produced":
            instance.produced[int(event["seq"])] = int(event["agent_steps"])
        elif kind == "sent":
            instance.sent[int(event["seq"])] = int(event["connection"])
        elif kind == "confirmed":
            instance.confirmed.append((int(event["connection"]), int(event["fragments"])))
        elif kind == "unconfirmed":
            pass
        elif kind == "refused":
            instance.refused.add(int(event["seq"]))
        elif kind == "garbage":
            instance.garbage[event.get("code", "")] += 1
        elif kind == "actor_stop":
            instance.stopped = True
        else:
            raise LedgerError(f"{path}: unknown actor event {kind!r}")
    return instances


def reconcile(learner_events: list[dict], actor_events: list[dict]) -> dict:
    learner = parse_learner(learner_events)
    actors = parse_actors(actor_events)
    durable = durable_updates(learner.segments)
    # Where the learner saw each fragment: (segment index, records).
    seen: dict[tuple[str, int], list[tuple[int, list]]] = defaultdict(list)
    for k, segment in enumerate(learner.segments):
        for key, records in segment.records.items():
            seen[key].append((k, records))

    classes: Counter = Counter()
    steps: Counter = Counter()
    per_actor: dict[str, Counter] = defaultdict(Counter)
    problems: Counter = Counter()
    produced_keys = set()
    for instance_id, instance in actors.items():
        for seq, agent_steps in instance.produced.items():
            key = (instance_id, seq)
            produced_keys.add(key)
            outcome = _classify(key, instance, seen.get(key, []), learner.segments, durable)
            if outcome.startswith("unexplained"):
                problems[outcome] += 1
                outcome = "unexplained"
            classes[outcome] += 1
            steps[outcome] += agent_steps
            per_actor[instance.name or instance_id][outcome] += 1
        # A stream's summary counts the fragments the learner accepted on it.
        for connection, fragments in instance.confirmed:
            on_it = [s for s, c in instance.sent.items() if c == connection]
            accepted = sum(
                1
                for s in on_it
                if any(kind == "accepted" for _, records in seen.get((instance_id, s), []) for kind, _ in records)
            )
            if accepted != fragments:
                problems["unexplained: a stream's confirmed count differs from the learner's"] += 1
    for key in seen:
        if key not in produced_keys:
            problems["unexplained: the learner recorded a fragment no actor ledger produced"] += 1

    for kind, count in learner.unattributed.items():
        if not kind.startswith("rejected"):
            problems[f"unexplained: {kind} records of an actor id no register line names"] += count

    garbage = Counter()
    for instance in actors.values():
        garbage.update(instance.garbage)
    undecodable = learner.unattributed.get("rejected:decode", 0)
    if garbage and undecodable != garbage.get("INVALID_ARGUMENT", 0):
        problems["unexplained: undecodable messages refused differ from those a client saw refused"] += 1
    unexplained = sum(problems.values())
    return {
        "produced": sum(classes.values()),
        "produced_agent_steps": sum(steps.values()),
        "classes": dict(sorted(classes.items(), key=lambda kv: _order(kv[0]))),
        "agent_steps": dict(sorted(steps.items(), key=lambda kv: _order(kv[0]))),
        "unexplained": unexplained,
        "problems": dict(problems),
        "unattributed_learner_records": dict(learner.unattributed),
        "garbage_sent": dict(garbage),
        "per_actor": {name: dict(c) for name, c in sorted(per_actor.items())},
        "learner_processes": len(learner.segments),
        "learner_clean_stops": sum(s.stopped for s in learner.segments),
        "actor_processes": len(actors),
        "actor_clean_stops": sum(a.stopped for a in actors.values()),
    }


def _classify(key, instance: ActorInstance, seen: list, segments: list[Segment], durable: list[int]) -> str:
    seq = key[1]
    if not seen:
        if seq in instance.refused:
            return "refused_by_transport"
        if seq in instance.sent:
            return "lost_in_transport"
        return "unsent_at_stop" if instance.stopped else "lost_with_actor"
    if len(seen) > 1:
        return "unexplained: one fragment seen by two learner processes"
    k, records = seen[0]
    kinds = [kind for kind, _ in records]
    if kinds.count("accepted") + kinds.count("rejected") != 1:
        return "unexplained: a fragment accepted or rejected more than once"
    if kinds[0] == "rejected":
        return "rejected:" + str(records[0][1]) if len(records) == 1 else "unexplained: a rejected fragment went on"
    ends = [(kind, detail) for kind, detail in records[1:]]
    if len(ends) > 1:
        return "unexplained: a fragment both trained on and dropped"
    if not ends:
        if segments[k].stopped:
            return "unexplained: accepted by a learner that stopped cleanly, never trained or dropped"
        return "lost_with_learner"
    kind, detail = ends[0]
    if kind == "dropped":
        return f"dropped:{detail}"
    return "trained" if int(detail) <= durable[k] else "lost_with_learner"


def _order(name: str) -> tuple[int, str]:
    base = name.split(":")[0]
    return (CLASSES.index(base) if base in CLASSES else len(CLASSES), name)


def format_table(summary: dict) -> str:
    produced = summary["produced"] or 1
    rows = [f"{'class':<28} {'fragments':>10} {'share':>7} {'agent-steps':>12}"]
    for name, count in summary["classes"].items():
        rows.append(
            f"{name:<28} {count:>10} {count / produced:>7.1%} {summary['agent_steps'].get(name, 0):>12}"
        )
    rows.append(f"{'produced':<28} {summary['produced']:>10} {'':>7} {summary['produced_agent_steps']:>12}")
    rows.append(
        f"learner processes {summary['learner_processes']} ({summary['learner_clean_stops']} stopped cleanly), "
        f"actor processes {summary['actor_processes']} ({summary['actor_clean_stops']} stopped cleanly)"
    )
    if summary["unattributed_learner_records"]:
        rows.append(f"learner records naming no registered actor: {summary['unattributed_learner_records']}")
    if summary["garbage_sent"]:
        rows.append(f"undecodable messages sent by test clients, by reply: {summary['garbage_sent']}")
    rows.append(f"unexplained: {summary['unexplained']}")
    for problem, count in summary["problems"].items():
        rows.append(f"  {count} × {problem}")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m junction.ledger",
        description="Reconcile a run's fragment ledgers: every produced fragment in exactly one class.",
    )
    parser.add_argument("learner", type=Path, help="RUN_DIR/ledger.jsonl")
    parser.add_argument("actors", type=Path, nargs="+", help="the actors' ledgers (actor --ledger FILE)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    args = parser.parse_args(argv)
    try:
        learner_events = read_lines(args.learner)
        actor_events = [e for path in args.actors for e in read_lines(path)]
        summary = reconcile(learner_events, actor_events)
    except (OSError, LedgerError, KeyError, TypeError, ValueError) as e:
        print(f"python -m junction.ledger: {e}", file=sys.stderr)
        return 2
    print(json.dumps(summary) if args.json else format_table(summary))
    return 1 if summary["unexplained"] else 0


if __name__ == "__main__":
    sys.exit(main())
