"""MetaDrive as a Junction actor: registers with `learner serve` over gRPC, runs MetaDrive's
multi-agent intersection or roundabout with the broadcast policy, and streams
`RolloutFragment`s in Junction's layout (observations through `metadrive_adapter`, neighbours
and LCF features, finished agent episodes, one `SceneEpisodeStats` per MetaDrive episode).

    python -m junction.metadrive_actor --learner http://HOST:PORT [--scene intersection]

The learner must run a MetaDrive scenario (`--scenario intersection-on-metadrive`); its name
is on every fragment. One connection per process: when the learner ends the run the actor
exits 0; when it goes away the actor exits 1 (scripts restart it; Rust actors reconnect).
"""

from __future__ import annotations

import argparse
import logging
import os
import queue
import signal
import socket
import sys
import threading
import time
import tomllib

import numpy as np

from . import _native
from .metadrive_env import MetaDriveScene, ScenarioError
from .policy import GaussianPolicy, PolicyError

PROTOCOL_VERSION = 1
ACTION_DIM = _native.ACTION_DIM
#: Fragments waiting for the stream; when full the simulation waits (backpressure).
OUTBOX = 4
log = logging.getLogger("junction.metadrive_actor")


class ActorError(RuntimeError):
    """Something that ends the actor with an error message."""


def proto():
    """The generated gRPC stubs (scripts/build-python.sh makes them from proto/)."""
    try:
        from ._proto import junction_pb2, junction_pb2_grpc
    except ImportError as e:
        raise ActorError(
            f"the gRPC stubs are missing ({e}): run scripts/build-python.sh"
        ) from None
    return junction_pb2, junction_pb2_grpc


class LcfColumn:
    """CoPO's per-agent LCF angle: drawn when an agent first appears in its slot, kept until
    its episode ends, appended to every row the policy sees (as `actor/src/lcf_column.rs`)."""

    def __init__(self, slots: int, rng: np.random.Generator):
        self.phi = np.zeros(slots, np.float32)
        self.has = np.zeros(slots, bool)
        self.rng = rng
        self.distribution = None

    def spawn(self, alive: np.ndarray) -> None:
        if self.distribution is None:
            return
        for slot in np.flatnonzero(alive & ~self.has):
            self.phi[slot] = self.distribution.sample(self.rng)
            self.has[slot] = True

    def finish(self, dones: np.ndarray) -> None:
        self.has &= ~dones
        self.phi[dones] = 0.0

    def rows(self, observations: np.ndarray, alive: np.ndarray) -> np.ndarray:
        if self.distribution is None:
            return observations
        column = np.where(alive, [_native.phi_observation(float(p)) for p in self.phi], 0.0)
        return np.concatenate([observations, column[:, None].astype(np.float32)], axis=1)


def collect(scene: MetaDriveScene, policy: GaussianPolicy, lcf: LcfColumn, steps: int,
            rng: np.random.Generator) -> dict:
    """`steps` steps of `scene`; the arrays of one fragment (rollout.rs's layout)."""
    slots = scene.slots
    obs, alive, actions, log_probs = [], [], [], []
    rewards, costs, dones, features = [], [], [], []
    offsets, ids = [0], []
    episodes, scene_episodes = [], []
    for _ in range(steps):
        lcf.spawn(scene.alive)
        rows = lcf.rows(scene.observations, scene.alive)
        a = np.zeros((slots, ACTION_DIM), np.float32)
        lp = np.zeros(slots, np.float32)
        live = np.flatnonzero(scene.alive)
        if live.size:
            a[live], lp[live] = policy.sample(rows[live], rng)
        obs.append(rows)
        alive.append(scene.alive.copy())
        actions.append(a)
        log_probs.append(lp)
        base = offsets[-1]
        offsets.extend(int(base + o) for o in scene.neighbour_offsets[1:])
        ids.append(scene.neighbour_ids)
        features.append(scene.lcf_features)
        result = scene.step(a)
        lcf.finish(result.dones)
        rewards.append(result.rewards)
        costs.append(result.costs)
        dones.append(result.dones)
        episodes.extend(row for _, row in result.finished)
        if result.scene_episode is not None:
            scene_episodes.append(result.scene_episode)
    last_alive, last_done = alive[-1], dones[-1]
    continuing = last_alive & ~last_done
    bootstrap = np.zeros_like(obs[-1])
    now = lcf.rows(scene.observations, scene.alive)
    bootstrap[continuing] = now[continuing]
    return dict(
        obs=np.stack(obs), alive=np.stack(alive), actions=np.stack(actions),
        log_probs=np.stack(log_probs), rewards=np.stack(rewards), costs=np.stack(costs),
        dones=np.stack(dones), features=np.stack(features), offsets=np.asarray(offsets, np.uint32),
        ids=np.concatenate(ids).astype(np.uint32) if ids else np.zeros(0, np.uint32),
        episodes=episodes, scene_episodes=scene_episodes, bootstrap=bootstrap,
    )


def fragment_message(pb, arrays: dict, actor_id: str, sequence: int, version: int, scenario: str,
                     dt: float):
    steps, agents, obs_dim = arrays["obs"].shape
    return pb.RolloutFragment(
        protocol_version=PROTOCOL_VERSION,
        actor_id=actor_id,
        sequence=sequence,
        behaviour_version=version,
        scenario=scenario,
        steps=steps,
        agents=agents,
        obs_dim=obs_dim,
        action_dim=ACTION_DIM,
        obs=arrays["obs"].ravel().tolist(),
        actions=arrays["actions"].ravel().tolist(),
        log_probs=arrays["log_probs"].ravel().tolist(),
        rewards=arrays["rewards"].ravel().tolist(),
        costs=arrays["costs"].ravel().tolist(),
        dones=arrays["dones"].astype(np.uint8).tobytes(),
        alive=arrays["alive"].astype(np.uint8).tobytes(),
        bootstrap_obs=arrays["bootstrap"].ravel().tolist(),
        neighbour_offsets=arrays["offsets"].tolist(),
        neighbour_ids=arrays["ids"].tolist(),
        episodes=[
            pb.EpisodeStats(outcome=o, length=n, total_reward=r, mean_abs_accel=ma,
                            max_abs_accel=xa, collisions=c, energy_kj=e, total_cost=k)
            for o, n, r, ma, xa, c, e, k in arrays["episodes"]
        ],
        sim_seconds=steps * dt,
        lcf_features=arrays["features"].ravel().tolist(),
        scene_episodes=[
            pb.SceneEpisodeStats(steps=s, successes=a, crashes=b, out_of_road=c, timeouts=d)
            for s, a, b, c, d in arrays["scene_episodes"]
        ],
    )


class Actor:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.pb, self.pb_grpc = proto()
        self.finished = threading.Event()
        self.failed: list[str] = []
        self.weights_lock = threading.Lock()
        self.weights = None
        self.weights_arrived = threading.Event()
        self.outbox: queue.Queue = queue.Queue(OUTBOX)

    def run(self) -> int:
        import grpc

        target = self.args.learner.removeprefix("http://")
        if "://" in target:
            raise ActorError(f"--learner {self.args.learner!r}: only http://HOST:PORT is supported")
        limit = self.args.max_message_bytes
        channel = grpc.insecure_channel(
            target,
            options=[("grpc.max_send_message_length", limit),
                     ("grpc.max_receive_message_length", limit)],
        )
        try:
            grpc.channel_ready_future(channel).result(timeout=self.args.connect_timeout)
        except grpc.FutureTimeoutError:
            raise ActorError(
                f"the learner at {self.args.learner} was not reachable within "
                f"{self.args.connect_timeout} s (--connect-timeout)"
            ) from None
        stub = self.pb_grpc.LearnerStub(channel)
        try:
            reply = stub.Register(self.pb.RegisterRequest(
                protocol_version=PROTOCOL_VERSION, actor_name=self.args.name, scenes=1),
                timeout=30)
        except grpc.RpcError as e:
            raise ActorError(f"registering with the learner: {e.details() or e}") from None
        scenario = self.check(reply)
        log.info("registered as %s, scenario %s", reply.actor_id, scenario.name)
        watcher = threading.Thread(target=self.watch, args=(stub, reply.actor_id), daemon=True)
        watcher.start()
        pusher = threading.Thread(target=self.push, args=(stub,), daemon=True)
        pusher.start()
        if not self.weights_arrived.wait(timeout=60):
            raise ActorError("the first policy did not arrive within 60 s")
        seed = (reply.run_seed ^ self.args.seed ^ sum(reply.actor_id.encode())) % 2**63
        rng = np.random.default_rng(seed)
        scene = MetaDriveScene(scenario, seed)
        lcf = LcfColumn(scene.slots, rng)
        version, policy, sequence = None, None, 0
        try:
            while not self.finished.is_set() and not self.failed:
                with self.weights_lock:
                    latest = self.weights
                if latest.version != version:
                    policy = self.load(latest, scenario)
                    version = latest.version
                    lcf.distribution = policy.lcf
                arrays = collect(scene, policy, lcf, reply.fragment_length, rng)
                message = fragment_message(self.pb, arrays, reply.actor_id, sequence, version,
                                           scenario.name, scene.dt)
                sequence += 1
                while not self.finished.is_set() and not self.failed:
                    try:
                        self.outbox.put(message, timeout=0.5)
                        break
                    except queue.Full:
                        continue
        finally:
            self.outbox.put(None)
            pusher.join(timeout=30)
            scene.close()
            channel.close()
        if self.failed and not self.finished.is_set():
            raise ActorError(self.failed[0])
        log.info("the learner finished the run")
        return 0

    def check(self, reply) -> _native.Scenario:
        """What the learner asks for, checked before anything is built for it."""
        if reply.protocol_version != PROTOCOL_VERSION:
            raise ActorError(f"the learner speaks protocol {reply.protocol_version}; "
                             f"this actor speaks {PROTOCOL_VERSION}")
        if not reply.actor_id:
            raise ActorError("the learner refused the registration (see its log)")
        if reply.obs_layout_version != _native.OBS_LAYOUT_VERSION:
            raise ActorError(f"the learner uses observation layout {reply.obs_layout_version}; "
                             f"this actor builds {_native.OBS_LAYOUT_VERSION}")
        scenario = _native.scenario_from_toml(reply.scenario_toml, [])
        table = tomllib.loads(scenario.toml)
        if table["simulator"] != "metadrive":
            raise ActorError(
                f"the learner trains {scenario.name!r} on Junction's simulator; start "
                "`target/release/actor` for it, or the learner with a MetaDrive scenario "
                "(--scenario intersection-on-metadrive)")
        if self.args.scene and table["kind"] != self.args.scene:
            raise ActorError(f"--scene {self.args.scene}: the learner's scenario "
                             f"{scenario.name!r} is a {table['kind']}")
        if reply.obs_dim not in (scenario.obs_dim, scenario.obs_dim + 1) \
                or reply.action_dim != ACTION_DIM:
            raise ActorError(f"the learner's dimensions {reply.obs_dim}×{reply.action_dim} do "
                             "not match its scenario")
        if not 1 <= reply.fragment_length <= 100_000:
            raise ActorError(f"the learner asks for fragments of {reply.fragment_length} steps")
        try:
            from .metadrive_env import metadrive_config

            metadrive_config(scenario)
        except ScenarioError as e:
            raise ActorError(str(e)) from None
        return scenario

    def load(self, weights, scenario) -> GaussianPolicy:
        if weights.protocol_version != PROTOCOL_VERSION or weights.format != "safetensors":
            raise ActorError(f"policy v{weights.version} comes in protocol "
                             f"{weights.protocol_version}, format {weights.format!r}")
        try:
            policy = GaussianPolicy(weights.data)
        except PolicyError as e:
            raise ActorError(f"policy v{weights.version}: {e}") from None
        columns = 1 if policy.lcf else 0
        if policy.obs_dim != scenario.obs_dim + columns or policy.action_dim != ACTION_DIM:
            raise ActorError(f"policy v{weights.version} takes {policy.obs_dim} values; the "
                             f"scenario has {scenario.obs_dim} (+{columns} for the LCF)")
        if weights.active_agents not in (0, scenario.slots):
            raise ActorError("the learner's curriculum changes the agent count, which MetaDrive "
                             "scenes cannot follow (learner.algo = \"cl\" is not supported)")
        log.info("acting with policy v%d", weights.version)
        return policy

    def watch(self, stub, actor_id: str) -> None:
        """Follows the policy stream: the newest weights, and the end of the run."""
        import grpc

        request = self.pb.WatchPolicyRequest(protocol_version=PROTOCOL_VERSION,
                                             actor_id=actor_id, have_version=0)
        try:
            for weights in stub.WatchPolicy(request):
                with self.weights_lock:
                    self.weights = weights
                self.weights_arrived.set()
                if weights.run_finished:
                    self.finished.set()
                    return
        except grpc.RpcError as e:
            if not self.finished.is_set():
                self.failed.append(f"the policy stream broke: {e.details() or e}")
            return
        if not self.finished.is_set():
            self.failed.append("the learner closed the policy stream")

    def push(self, stub) -> None:
        """Streams the outbox; the learner's flow control holds it back when it is busy."""
        import grpc

        def fragments():
            while True:
                message = self.outbox.get()
                if message is None:
                    return
                yield message

        try:
            summary = stub.PushRollouts(fragments())
            log.info("rollout stream closed: %d fragments, %d agent-steps accepted",
                     summary.accepted_fragments, summary.accepted_agent_steps)
        except grpc.RpcError as e:
            # The learner ends the stream when its run is over; that is not a failure.
            time.sleep(0.5)
            if not self.finished.is_set():
                self.failed.append(f"the rollout stream broke: {e.details() or e}")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m junction.metadrive_actor",
        description="MetaDrive's multi-agent scenes as an actor of `learner serve` (gRPC).",
    )
    p.add_argument("--learner", required=True, metavar="http://HOST:PORT",
                   help="the learner's gRPC address")
    p.add_argument("--scene", choices=["intersection", "roundabout"],
                   help="refuse a learner whose scenario is another kind of scene")
    p.add_argument("--seed", type=int, default=0,
                   help="mixed with the run's seed and the actor id into the actor's seed")
    p.add_argument("--name", default=f"{socket.gethostname()}/{os.getpid()}/metadrive",
                   help="shown in the learner's logs")
    p.add_argument("--connect-timeout", type=float, default=120.0, metavar="SECONDS",
                   help="how long to wait for the learner to be reachable")
    p.add_argument("--max-message-bytes", type=int, default=64 << 20,
                   help="gRPC message limit")
    p.add_argument("--torch-threads", type=int, default=1,
                   help="PyTorch threads for inference (MetaDrive itself is single-threaded)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    import torch

    torch.set_num_threads(max(args.torch_threads, 1))
    # SIGTERM stops like Ctrl-C.
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    try:
        return Actor(args).run()
    except ActorError as e:
        log.error("%s", e)
        return 1
    except KeyboardInterrupt:
        log.info("stopped")
        return 0


if __name__ == "__main__":
    sys.exit(main())
