"""Training applications: the gymnasium environment over the training diagram (``env``), the
rollout workers (``rollout``; Ray: ``workers``) and the training run (``trainer``:
``ace-drake train``). The maths they use is in ``ace_drake.learning``."""
