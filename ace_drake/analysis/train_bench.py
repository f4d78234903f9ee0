"""``ace-drake bench train``: collection and learning throughput of the training machinery
(issue 7), measured side by side in one run:

- environment steps per second (32 ms steps of the training diagram, resets included) of the
  rollout workers playing the freshly initialised actor (``mode="policy"``) on Ray, with 1 and
  with 2 workers (each with one task of ``episodes`` episodes in flight until ``seconds`` of
  collection have passed), and the speed-up of 2 over 1;
- learner updates per second (``SacLearner.update`` on batches from an ``EventReplay`` filled
  with the collected episodes, one torch thread), median over chunks of 20 updates;
- the ratio of updates per second to environment steps per second with 2 workers: the update-
  to-data ratio the learner can sustain (``TrainConfig.updates_per_step`` above it leaves the
  workers waiting, below it the learner).

On a 2-core machine the 2-worker figure shares the cores with the learner's process only while
it waits, so it is the collection's upper bound.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from ace_drake.artefacts import provenance
from ace_drake.learning.replay import EventReplay
from ace_drake.learning.sac import SacConfig, SacLearner
from ace_drake.training.workers import WorkerPool


def _collect(workers: int, seconds: float, episodes: int, seed: int, progress, batch: int | None = None) -> tuple[float, list]:
    """Steps per wall second of ``workers`` Ray workers over ``seconds``, and the episodes: each a
    ``RolloutWorker`` (one RallyEnv), or with ``batch`` a ``VectorRolloutWorker`` of that many
    environments on the segment-stepped diagram."""

    pool = WorkerPool(workers, {"seed": seed} if batch is None else {"seed": seed, "batch": batch}, "ray")
    try:
        for index in range(workers):  # warm-up: building the diagram, fitting the shot distribution
            pool.submit(index, 1, "policy")
        while pool.in_flight:
            pool.wait()
        collected, steps = [], 0
        start = time.perf_counter()
        for index in range(workers):
            pool.submit(index, episodes, "policy")
        while pool.in_flight:
            index, episodes_done = pool.wait()
            collected += episodes_done
            steps += sum(episode.steps for episode in episodes_done)
            if time.perf_counter() - start < seconds:
                pool.submit(index, episodes, "policy")
        wall = time.perf_counter() - start
    finally:
        pool.shutdown()
    kind = "RallyEnv" if batch is None else f"RallyVectorEnv B = {batch}"
    progress(f"bench train: {workers} worker(s), {kind}: {steps} steps in {wall:.1f} s ({steps / wall:.0f} steps/s)")
    return steps / wall, collected


def bench_train(seconds: float = 60.0, episodes: int = 2, updates: int = 200, seed: int = 0, batches=(1, 16, 64, 256), progress=print) -> dict:
    """The figures of the module docstring (keys ``env_steps_per_s`` {1, 2}, ``worker_speedup``,
    ``vector_env_steps_per_s`` {B: steps/s of 2 workers of B environments each},
    ``ratio_env_steps_new_to_old``, ``updates_per_s`` {threads}, ``updates_per_env_step``), with
    the provenance (command, date). A vector worker's task plays until ``episodes`` x B episodes
    have ended."""

    rates, episodes_played = {}, []
    for workers in (1, 2):
        rates[workers], played = _collect(workers, seconds, episodes, seed, progress)
        episodes_played += played
    vector_rates = {}
    for batch in batches:
        vector_rates[batch], played = _collect(2, seconds, episodes * batch, seed, progress, batch=batch)
        episodes_played += played[:200]
    best = max(vector_rates.values()) if vector_rates else None
    learner = SacLearner(SacConfig(seed=seed))
    replay = EventReplay(layout=learner.config.layout)
    for episode in episodes_played:
        replay.add_episode(episode.transitions, episode.summary)
    updates_per_s = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        chunk, times = 20, []
        for _ in range(max(1, updates // chunk)):
            start = time.perf_counter()
            for _ in range(chunk):
                learner.update(replay.sample(learner.config.batch_size))
            times.append((time.perf_counter() - start) / chunk)
        updates_per_s[threads] = 1.0 / float(np.median(times))
        progress(f"bench train: {updates_per_s[threads]:.1f} updates/s (batch {learner.config.batch_size}, {threads} torch thread(s))")
    torch.set_num_threads(1)
    collection = best if best is not None else rates[2]
    return {
        "env_steps_per_s": {str(k): round(v, 2) for k, v in rates.items()},
        "worker_speedup": round(rates[2] / rates[1], 3),
        "vector_env_steps_per_s": {str(k): round(v, 1) for k, v in vector_rates.items()},
        "ratio_env_steps_new_to_old": round(best / rates[2], 2) if best is not None else None,
        "updates_per_s": {str(k): round(v, 2) for k, v in updates_per_s.items()},
        "updates_per_env_step": round(max(updates_per_s.values()) / collection, 4),
        "batch_size": learner.config.batch_size,
        "seconds_per_collection": seconds,
        "episodes_collected": len(episodes_played),
        **provenance(),
    }
