"""Tutorial 06: training a rally policy with SAC, end to end, in a few minutes.

Read this file top to bottom like a notebook. The paper's policy is trained with Soft
Actor-Critic (Methods *Algorithm*); this tutorial runs the same machinery as
``ace-drake train models/train_rally_paper.yaml``, only very small, so that every part shows:

  1. the environment: one episode of ``RallyEnv`` (the training diagram: ball, robot, the cheap
     statistical sensors, control stack) played by a rollout worker, what a transition holds;
  2. the learner: the actor (a tanh-squashed Gaussian with the auxiliary ball-state decoder), the
     twin critics on the privileged ground truth, and one update's losses;
  3. a training run: returner demonstrations, Ornstein-Uhlenbeck exploration, a cloning phase and
     asynchronous SAC with Ray workers (``--backend local`` runs everything in this process),
     checkpointed in ``--out``; run the tutorial again and it resumes from the checkpoint; the
     same run resumed from its checkpoint carried to another directory, as on another machine;
  4. evaluation and export: the trained actor in the rally diagram, the policy artefact, its
     sidecar and the learning curve;
  5. the hit-state action (this project's; docs/training.md, *Hit-state actor*): an actor that
     outputs the joints' state at the predicted hit, the fixed layer that turns it into the
     eq. (12) action, a demonstration episode through that layer, and the cloning loss.
  6. mirror augmentation (paper, *Algorithm*): the robot is its own mirror image across the
     table's XZ plane, so every transition has an exact mirrored twin (``mirror: true`` stores both).

A policy trained for a few hundred steps does not return balls; the numbers printed are what it
does. Run it from the repository root:

    .venv/bin/python tutorials/06_training.py                 # Ray, 2 workers
    .venv/bin/python tutorials/06_training.py --backend local # one process
    .venv/bin/python tutorials/06_training.py --out DIR

It writes run/ (checkpoint, TensorBoard logs: ``tensorboard --logdir DIR/run``) and policies/
(tutorial.pt, tutorial.json, tutorial_curve.png) into --out (default out/tutorials/06).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from ace_drake.config import ConfigError
from ace_drake.control.params import RallyParams, ReturnerParams
from ace_drake.learning.sac import SacConfig, SacLearner, load_policy
from ace_drake.training.checkpoint import CHECKPOINT, PORTABLE_CHECKPOINT
from ace_drake.training.export import export
from ace_drake.training.loop import TrainConfig, Trainer
from ace_drake.training.rollout import RolloutWorker

PARTS = ("positions", "spins", "robot_state", "end_effector", "skill", "estimate", "estimate_status", "hit_prediction")
REPO_ROOT = Path(__file__).resolve().parents[1]
# A small learner, so that the tutorial's updates take milliseconds.
SMALL = SacConfig(batch_size=64, actor_hidden=(64, 64), embedding_size=64, decoder_hidden=(32,), critic_hidden=(64, 64), bc_weight=1.0)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "tutorials" / "06")
    parser.add_argument("--backend", choices=("ray", "local"), default="ray")
    parser.add_argument("--steps", type=int, default=400, help="environment steps of the whole run")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    # ------------------------------------------------------------------ 1. the environment
    print("1. one episode of the rally environment (Ornstein-Uhlenbeck exploration)")
    worker = RolloutWorker(sac=SMALL, seed=0)
    (episode,) = worker.collect(1, "ou")
    t = episode.transitions
    layout = worker.env.layout
    print(f"   {episode.steps} steps of 32 ms; ended by '{episode.end}' with outcome '{episode.outcome}', reward {t['reward'][-1]:+.2f}")
    print(f"   actor observation: {t['obs'].shape[1]} numbers ({', '.join(f'{p} {layout.slice(p).stop - layout.slice(p).start}' for p in PARTS)})")
    print(f"   critic's privileged observation: {t['privileged'].shape[1]} numbers (true ball state, joint state, skill)")
    # The hit predicted from the EKF's estimate (control.hit_prediction): where the memoryless
    # returner would meet the ball. An actor may read it instead of learning the flight itself.
    predicted = [layout.part(obs, "hit_prediction") for obs in t["obs"]]
    first = next((k for k, hit in enumerate(predicted) if hit[0] > 0.5), None)
    if first is None:
        print("   no hit was predicted in this episode (the ball never had a bounce on the robot's half ahead)")
    else:
        hit = predicted[first]
        print(f"   step {first}: hit predicted {hit[1]:.3f} s ahead, ball at ({hit[2]:.2f}, {hit[3]:.2f}, {hit[4]:.2f}) m moving {np.linalg.norm(hit[5:8]):.1f} m/s")
    print(f"   closest approach of the ball to the blade centre: {episode.summary.closest_approach:.2f} m")

    # ------------------------------------------------------------------ 2. the learner
    print("2. the learner: one SAC update on that episode's transitions")
    learner = SacLearner(SMALL)
    batch = {key: np.repeat(value, -(-SMALL.batch_size // episode.steps), axis=0)[: SMALL.batch_size] for key, value in t.items()}
    losses = learner.update(batch)
    print("   " + ", ".join(f"{key} {value:.4f}" for key, value in losses.items()))

    # ------------------------------------------------------------------ 3. a training run
    print(f"3. a training run of {args.steps} steps ({args.backend} backend), checkpointed in {args.out / 'run'}")
    config = TrainConfig(
        name="tutorial", seed=0, env_steps=args.steps, workers=2 if args.backend == "ray" else 1, backend=args.backend,
        episodes_per_task=2, demonstrations=4, ou_episodes=4, pretrain_updates=100, update_chunk=20,
        updates_per_step=0.5, checkpoint_every=100, evaluate_every=200, evaluation_episodes=5, log_every=10.0, sac=SMALL,
    )
    trainer = Trainer(config, args.out / "run", progress=lambda line: print("   " + line))
    state = trainer.run()
    print(f"   {state.env_steps} steps, {state.episodes} episodes, {trainer.learner.updates} updates, {state.wall_time:.0f} s")
    # A run moved to a machine without its run directory resumes from its checkpoint carried there
    # (ace-drake train --resume-from): the whole one with its tables, the portable one (networks,
    # optimisers, counters, no tables: ~7 MB where the paper run's whole one is ~2.4 GB) with its
    # tables filling anew. To learn on from a portable one, a run whose actor loss has a cloning
    # term needs labels to come (learn_mode: dagger); this small run's would not come, and extended
    # (env_steps) it is refused.
    for name, carried in (("moved", CHECKPOINT), ("moved_portable", PORTABLE_CHECKPOINT)):
        if not (args.out / name / CHECKPOINT).is_file():  # (run again, the tutorial resumes there too)
            moved = Trainer(config, args.out / name, progress=lambda line: None, resume_from=args.out / "run" / carried)
            print(f"   {carried} carried to {args.out / name}: resumed at {moved.state.env_steps} steps with {len(moved.replay)} replay rows")
    try:
        Trainer(dataclasses.replace(config, env_steps=2 * args.steps), args.out / "moved_portable", progress=lambda line: None)
    except ConfigError as error:
        print(f"   extended, the portable one is refused: {str(error).split('), and ', 1)[-1]}")

    # ------------------------------------------------------------------ 4. evaluation and export
    print("4. evaluation in the rally diagram and export")
    for steps, updates, figures in state.evaluations:
        print(f"   after {steps} steps / {updates} updates: returned {figures['returned']} of {figures['played']} playable shots")
    sidecar = export(trainer, args.out / "policies", "final")
    policy = load_policy(args.out / "policies" / "tutorial.pt")
    print(f"   wrote {args.out / 'policies'}/tutorial.pt ({sum(p.numel() for p in policy.parameters())} parameters), "
          f"tutorial.json and tutorial_curve.png; the sidecar records {sidecar['env_steps']} steps, seed {sidecar['seed']}")
    print("   in a rally: ace-drake evaluate --controller policy:<name> runs a policy in models/policies/")
    assert RallyParams().position_history == SMALL.position_history  # the diagram builds what the actor reads

    # ------------------------------------------------------------------ 5. the hit-state action
    print("5. the hit-state action: the actor names the joints' state at the hit, a fixed layer drives there")
    hit_config = dataclasses.replace(SMALL, action="hit_state", actor_observation_parts=PARTS)
    # The demonstrator: the memoryless returner's planned hit state, played through the layer.
    worker = RolloutWorker(sac=hit_config, seed=1, returner=ReturnerParams(memory=False))
    (episode,) = worker.collect(1, "demonstrator")
    t = episode.transitions
    labelled = np.all(np.isfinite(t["demo_action"]), axis=-1)
    print(f"   a demonstration: {episode.steps} steps, outcome '{episode.outcome}'; {labelled.sum()} steps carry the "
          f"returner's planned hit state as a label (the rest: no plan at the predicted hit)")
    first = int(np.argmax(labelled)) if labelled.any() else None
    if first is not None:
        layer = worker.layer
        q0 = layout.part(t["obs"][first], "robot_state")[:8]
        q_hit, v_hit = layer.parameterisation.hit_state(t["demo_action"][first].astype(float), q0)
        steps = int(layer.steps_to_hit(layout.part(t["obs"][first], "hit_prediction")[1]))
        print(f"   step {first}: hit {steps} segments ahead; the planned hit moves the joints by up to "
              f"{np.max(np.abs(q_hit - q0)):.2f} (rad or m), the fastest joint at {np.max(np.abs(v_hit)):.2f} at the hit")
        learner = SacLearner(hit_config)
        rows = {"obs": t["obs"][labelled], "demo_action": t["demo_action"][labelled]}
        print(f"   the untrained actor's cloning loss on them (task space + joints + consistency): "
              f"{learner.behaviour_cloning_loss(rows).item():.1f}")
        # The layer that meets the ball (PlayOptions.meet_ball): an actor's hit state a little off
        # (here the plan with a 0.05 rad shoulder error) is moved so the blade meets the predicted ball.
        from ace_drake.control.hit_state import HitStateLayer

        meeting = HitStateLayer.for_rally(worker.env.params.rally, meet_ball=True)
        ball = layout.part(t["obs"][first], "hit_prediction")[2:5]

        def miss(q):
            X_WR = meeting.model.racket_pose(q)
            return 100 * np.linalg.norm(ball - meeting.standoff * X_WR.rotation().matrix()[:, 2] - X_WR.translation())

        off = q_hit + np.r_[0.0, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0]
        print(f"   meeting the ball: the blade's contact point {miss(q_hit):.1f} cm from the predicted ball for the plan, "
              f"{miss(off):.1f} cm for the off hit state, {miss(meeting.meet_ball(off, ball)):.1f} cm once the layer has moved it")

    # ------------------------------------------------------------------ 6. mirror augmentation
    print("6. mirror augmentation: every transition and its mirror image across the table's XZ plane")
    from ace_drake.learning.mirror import Mirror
    from ace_drake.robot.model import RobotModel

    model = RobotModel()
    mirror = Mirror.from_robot(model, layout)  # checks the robot by forward kinematics and its limits first
    print(f"   joints map q -> s q + c: signs {mirror.joints.signs.astype(int).tolist()}, gantry_y offset {mirror.joints.offsets[1]:+.2f} m")
    q = np.random.default_rng(0).uniform(model.lower, model.upper)  # any configuration, the yaw too
    X, X_mirrored = model.racket_pose(q), model.racket_pose(mirror.joints.positions(q))
    gap = np.linalg.norm(X_mirrored.translation() - X.translation() * [1, -1, 1])
    print(f"   at a random configuration (yaw {q[2]:+.2f} rad) the mirrored joint state puts the racket {1000 * gap:.4f} mm "
          "from the mirrored racket: the arm turns about its own pivot")
    twin = mirror.transitions(t)
    back = mirror.transitions(twin)
    print(f"   a mirrored episode: ball y flipped ({t['obs'][0][layout.slice('positions')][1]:+.3f} -> {twin['obs'][0][layout.slice('positions')][1]:+.3f} m), "
          f"rewards kept, mirrored twice = itself to {max(np.max(np.abs(back[key] - t[key])) for key in ('obs', 'privileged', 'action')):.1e}")
    print("   a training config turns it on with `mirror: true` (models/train_rally_paper.yaml)")
    print("done")


if __name__ == "__main__":
    main()
