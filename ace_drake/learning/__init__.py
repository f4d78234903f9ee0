"""Learning maths: the learner (SAC with the auxiliary decoder loss and an optional cloning term),
its networks, event tables and hindsight relabelling (``replay``), the terminal reward (eq. 10),
mirroring, and the hit-state action's torch kinematics and cloning loss (``hit_state``). Plain
NumPy and torch: no Drake. The environment, the rollout workers and the training run that use
them are in ``ace_drake.training``.
"""
