"""Reads a run directory's TensorBoard event files with TensorBoard's own reader and prints
every scalar as JSON: {tag: [[step, wall_time, value], ...]} (tests/tests/tensorboard.rs)."""

import json
import sys

from tensorboard.backend.event_processing import event_accumulator

accumulator = event_accumulator.EventAccumulator(
    sys.argv[1], size_guidance={event_accumulator.SCALARS: 0}  # 0: keep every event
)
accumulator.Reload()
print(
    json.dumps(
        {
            tag: [[e.step, e.wall_time, e.value] for e in accumulator.Scalars(tag)]
            for tag in accumulator.Tags()["scalars"]
        }
    )
)
