#!/usr/bin/env python3
"""The hostile client of the chaos soak (scripts/chaos_soak.py, issue 42): registers with the
learner like an actor, then sends fragments no real actor sends, each on a rollout stream of
its own (a refused fragment ends its stream):

  stale      well-formed, but its behaviour version is 1000 past the learner's: accepted, then
             dropped as `stale` by the trainer (PushSummary says 1 accepted)
  oversized  larger than the learner's server.max_message_bytes: refused by the transport
             (OUT_OF_RANGE / RESOURCE_EXHAUSTED) before the learner sees it
  nan        well-formed but for a NaN observation: INVALID_ARGUMENT (non_finite)
  short      one observation value missing: INVALID_ARGUMENT (shape)

It keeps a fragment ledger like an actor's (`--ledger`; /tmp/spec/ledger.md, the line names of
common/src/ledger.rs): actor_start, produced, sent, then confirmed or unconfirmed per stream,
`refused` (with the status code) for a fragment the transport refused, actor_stop. Prints one
JSON line (what each stream got back) and exits 0 when every answer is the expected one, 1
otherwise, 2 when it could not reach the learner.

Needs grpcio and the stubs of `make python` (junction._proto); run with PYTHONPATH=python.
"""

import argparse
import json
import math
import os
import re
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LCF_FEATURES = 5


def protocol_version() -> int:
    """The wire protocol version the binaries speak (core/src/spec.rs)."""
    try:
        text = (ROOT / "core/src/spec.rs").read_text()
        return int(re.search(r"pub const PROTOCOL_VERSION: u32 = (\d+);", text).group(1))
    except (OSError, AttributeError):
        return 1


class Ledger:
    def __init__(self, path: str | None, instance: str):
        self.fd = None
        self.instance = instance
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def write(self, event: str, **fields):
        if self.fd is None:
            return
        line = json.dumps({"event": event, "instance": self.instance, **fields},
                          separators=(",", ":")) + "\n"
        os.write(self.fd, line.encode())  # one write(2) on O_APPEND: never half a line


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--learner", required=True, help="HOST:PORT of the learner's gRPC (TLS)")
    ap.add_argument("--tls-ca", required=True)
    ap.add_argument("--tls-domain", default=None)
    ap.add_argument("--auth-token-file", required=True)
    ap.add_argument("--ledger", default=None)
    ap.add_argument("--name", default="hostile")
    ap.add_argument("--max-message-bytes", type=int, default=4 << 20,
                    help="the learner's server.max_message_bytes: the oversized fragment exceeds it")
    ap.add_argument("--connect-timeout", type=float, default=60.0)
    args = ap.parse_args()

    import grpc
    from junction._proto import junction_pb2 as pb
    from junction._proto import junction_pb2_grpc as pb_grpc

    instance = f"{args.name}-{os.getpid()}-{time.time_ns():x}"
    ledger = Ledger(args.ledger, instance)
    token = Path(args.auth_token_file).read_text().strip()
    metadata = (("authorization", f"Bearer {token}"),)
    options = [("grpc.max_send_message_length", -1),
               ("grpc.max_receive_message_length", 64 << 20)]
    if args.tls_domain:
        options.append(("grpc.ssl_target_name_override", args.tls_domain))
    creds = grpc.ssl_channel_credentials(root_certificates=Path(args.tls_ca).read_bytes())
    channel = grpc.secure_channel(args.learner, creds, options=options)
    stub = pb_grpc.LearnerStub(channel)
    version = protocol_version()
    result = {"instance": instance, "streams": [], "ok": True}

    # Register (retrying while the learner is away: the soak may have just restarted it).
    hello = dict(protocol_version=version, actor_name=args.name, scenes=1)
    if "instance" in pb.RegisterRequest.DESCRIPTOR.fields_by_name:
        hello["instance"] = instance
    deadline = time.monotonic() + args.connect_timeout
    while True:
        try:
            reply = stub.Register(pb.RegisterRequest(**hello), metadata=metadata, timeout=10)
            status = stub.Status(pb.StatusRequest(), metadata=metadata, timeout=10)
            break
        except grpc.RpcError as e:
            if e.code() != grpc.StatusCode.UNAVAILABLE or time.monotonic() > deadline:
                result.update(ok=False, error=f"register: {e.code().name}: {e.details()}")
                print(json.dumps(result), flush=True)
                return 2
            time.sleep(1.0)
    ledger.write("actor_start", transport="grpc", name=args.name, pid=os.getpid())

    scenario = tomllib.loads(reply.scenario_toml)
    steps, agents = reply.fragment_length, int(scenario["agents"])
    obs_dim, action_dim = reply.obs_dim, reply.action_dim
    cells = steps * agents
    result.update(actor_id=reply.actor_id, policy_version=status.policy_version,
                  steps=steps, agents=agents, obs_dim=obs_dim)

    def fragment(seq: int, behaviour_version: int, obs_values: int | None = None,
                 nan: bool = False):
        obs = [0.01] * (cells * obs_dim if obs_values is None else obs_values)
        if nan:
            obs[len(obs) // 2] = math.nan
        return pb.RolloutFragment(
            protocol_version=version, actor_id=reply.actor_id, sequence=seq,
            behaviour_version=behaviour_version, scenario=scenario["name"], steps=steps,
            agents=agents, obs_dim=obs_dim, action_dim=action_dim, obs=obs,
            actions=[0.0] * (cells * action_dim), log_probs=[-1.0] * cells,
            rewards=[0.0] * cells, costs=[0.0] * cells, dones=bytes(cells),
            alive=bytes([1]) * cells, bootstrap_obs=[0.01] * (agents * obs_dim),
            neighbour_offsets=[0] * (cells + 1), neighbour_ids=[],
            lcf_features=[0.0] * (cells * LCF_FEATURES), sim_seconds=steps * 0.1)

    # Over the limit by a quarter: obs values of 4 bytes each, packed.
    oversized_values = (args.max_message_bytes + args.max_message_bytes // 4) // 4
    plan = [
        ("stale", dict(behaviour_version=status.policy_version + 1000), "OK"),
        ("oversized", dict(behaviour_version=status.policy_version,
                           obs_values=oversized_values), "TRANSPORT"),
        ("nan", dict(behaviour_version=status.policy_version, nan=True), "INVALID_ARGUMENT"),
        ("short", dict(behaviour_version=status.policy_version, obs_values=cells * obs_dim - 1),
         "INVALID_ARGUMENT"),
        ("stale", dict(behaviour_version=status.policy_version + 1000), "OK"),
    ]
    for connection, (kind, params, expect) in enumerate(plan, start=1):
        seq = connection - 1
        message = fragment(seq, **params)
        ledger.write("produced", seq=seq, agent_steps=cells)
        ledger.write("sent", seq=seq, connection=connection)
        entry = {"kind": kind, "seq": seq, "bytes": message.ByteSize(), "expect": expect}
        try:
            summary = stub.PushRollouts(iter([message]), metadata=metadata, timeout=60)
            ledger.write("confirmed", connection=connection, fragments=summary.accepted_fragments)
            entry.update(code="OK", accepted=summary.accepted_fragments)
            good = expect == "OK" and summary.accepted_fragments == 1
        except grpc.RpcError as e:
            code = e.code().name
            entry.update(code=code, details=(e.details() or "")[:200])
            if code in ("OUT_OF_RANGE", "RESOURCE_EXHAUSTED"):
                # Refused by the transport's size limit: the learner never saw it.
                ledger.write("refused", seq=seq, code=code)
                good = expect == "TRANSPORT"
            else:
                ledger.write("unconfirmed", connection=connection, fragments=1)
                good = code == expect
        entry["as_expected"] = good
        result["ok"] &= good
        result["streams"].append(entry)
    ledger.write("actor_stop", unsent=0)
    channel.close()
    print(json.dumps(result), flush=True)
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
