"""Parallel rollout workers on Ray, asynchronous with the learner (issue 7; paper, Methods
*Algorithm*: "several rollout workers ... asynchronous with the learner").

``WorkerPool`` runs ``rollout.RolloutWorker``s either as Ray actors (``backend="ray"``: an
in-process local cluster by default, or an existing cluster at ``address``, e.g.
``"ray://head:10001"``, to scale out to many machines) or in this process (``backend="local"``:
one worker, tasks run when their result is asked for; for debugging with a plain stack trace).

The learner keeps one task in flight per worker: ``submit(index, episodes, mode)`` starts one,
``wait()`` returns the first finished (worker index, episodes), and ``publish(actor_state)``
sends fresh actor weights that every *subsequently submitted* task plays with (Ray ships them
once through its object store; a worker loads them when its next task starts).

A task that raises (an environment whose simulation fails, say), or whose worker process dies (or
is killed by Ray's memory monitor), surfaces from ``wait()`` as a ``WorkerFailed`` naming the
worker; its environments are then in an unknown state, so the caller either stops or
``replace``s the worker with a fresh one (other seed) and submits to it again (``loop.Trainer``:
logged, counted, bounded by ``TrainConfig.max_worker_failures``).
"""

from __future__ import annotations

import traceback
from collections import deque

import ray

from ace_drake.training.rollout import ACTOR_MODES, RolloutWorker, VectorRolloutWorker

BACKENDS = ("ray", "local")


class WorkerFailed(RuntimeError):
    """A rollout worker's task raised, or its process died: ``index`` is the worker, ``cause`` the
    error (with Ray a ``RayTaskError``, whose message holds the worker's traceback, a
    ``RayActorError`` or an ``OutOfMemoryError``), ``error`` one line saying what was raised
    ("ValueError: ..."), ``traceback`` the whole story as text; the task's episodes are lost."""

    def __init__(self, index: int, cause: BaseException):
        self.index, self.cause = index, cause
        if isinstance(cause, ray.exceptions.RayError):  # the worker's traceback is in the message
            lines = [line for line in str(cause).splitlines() if line.strip()]
            self.error = lines[-1].strip() if lines else type(cause).__name__
            self.traceback = str(cause).strip()
        else:  # raised in this process (the local backend)
            self.error = traceback.format_exception_only(cause)[-1].strip()
            self.traceback = "".join(traceback.format_exception(cause)).strip()
        super().__init__(f"rollout worker {index} failed: {self.error}")


class WorkerPool:
    """``count`` rollout workers (module docstring). ``worker_args``: the keyword arguments of
    ``RolloutWorker`` shared by all (``env_params``, ``sac``, ``seed``, ``exploration``); worker
    i gets ``index=i``. With a ``batch`` among them, each worker is a ``VectorRolloutWorker``
    stepping that many environments on the segment-stepped diagram."""

    def __init__(self, count: int, worker_args: dict, backend: str = "ray", address: str | None = None):
        if backend not in BACKENDS:
            raise ValueError(f"WorkerPool: backend must be one of {BACKENDS}, got {backend!r}")
        if count < 1:
            raise ValueError(f"WorkerPool: count must be >= 1, got {count}")
        if backend == "local" and count != 1:
            raise ValueError("WorkerPool: the local backend runs exactly one worker (use backend 'ray' for more)")
        self.backend = backend
        self.count = count
        worker_class = VectorRolloutWorker if "batch" in worker_args else RolloutWorker
        self._actor_ref = None
        self._actor_state = None
        self._pending: dict = {}  # ray: object ref -> worker index (the local backend: _queue)
        if backend == "ray":
            if not ray.is_initialized():
                if address:
                    ray.init(address=address, log_to_driver=False)
                else:  # a local cluster: this machine's cores, no dashboard
                    ray.init(include_dashboard=False, log_to_driver=False, configure_logging=False)
            remote = ray.remote(num_cpus=1)(worker_class)
            self._new_worker = lambda args, index: remote.remote(**args, index=index)
        else:
            self._new_worker = lambda args, index: worker_class(**args, index=index)
            self._queue: deque = deque()
        self._workers = [self._new_worker(worker_args, i) for i in range(count)]

    def replace(self, index: int, worker_args: dict) -> None:
        """Worker ``index`` replaced by a fresh one made with ``worker_args`` (as the pool's, with
        e.g. another seed); its tasks in flight are dropped."""
        if self.backend == "ray":
            ray.kill(self._workers[index])
            self._pending = {ref: i for ref, i in self._pending.items() if i != index}
        else:
            self._queue = deque(task for task in self._queue if task[0] != index)
        self._workers[index] = self._new_worker(worker_args, index)

    def publish(self, actor_state: dict) -> None:
        """Fresh actor weights for the tasks submitted from now on."""
        if self.backend == "ray":
            self._actor_ref = ray.put(actor_state)
        else:
            self._actor_state = actor_state

    def submit(self, index: int, episodes: int, mode: str) -> None:
        """Starts worker ``index`` playing ``episodes`` episodes in ``mode`` (rollout.MODES) with
        the last published weights."""
        worker = self._workers[index]
        if self.backend == "ray":
            if self._actor_ref is not None and mode in ACTOR_MODES:
                worker.set_actor.remote(self._actor_ref)  # actor tasks run in order: before the collect
            self._pending[worker.collect.remote(episodes, mode)] = index
        else:
            self._queue.append((index, episodes, mode, self._actor_state if mode in ACTOR_MODES else None))

    @property
    def in_flight(self) -> int:
        return len(self._pending) if self.backend == "ray" else len(self._queue)

    def wait(self, timeout: float | None = None):
        """(worker index, episodes) of the first finished task, or None after ``timeout`` s.
        Raises WorkerFailed if that task raised."""
        if self.backend == "ray":
            if not self._pending:
                raise RuntimeError("WorkerPool.wait: no task in flight")
            done, _ = ray.wait(list(self._pending), num_returns=1, timeout=timeout)
            if not done:
                return None
            index = self._pending.pop(done[0])
            try:
                return index, ray.get(done[0])
            except ray.exceptions.RayError as error:  # raised, the process died, or Ray killed it (out of memory)
                raise WorkerFailed(index, error) from error
        if not self._queue:
            raise RuntimeError("WorkerPool.wait: no task in flight")
        index, episodes, mode, actor_state = self._queue.popleft()
        if actor_state is not None:
            self._workers[index].set_actor(actor_state)
        try:
            return index, self._workers[index].collect(episodes, mode)
        except Exception as error:  # the local backend's plain traceback stays chained
            raise WorkerFailed(index, error) from error

    def shutdown(self) -> None:
        """Stops the workers (and a local Ray cluster this pool started)."""
        if self.backend == "ray":
            for worker in self._workers:
                ray.kill(worker)
            self._pending.clear()
            if ray.is_initialized():
                ray.shutdown()
