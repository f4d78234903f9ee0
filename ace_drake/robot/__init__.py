"""The robot: its model (``model``: the SDFormat file in models/ with its scenario), compiled
kinematics bounds (``bounds``), the racket's batched forward kinematics (``kinematics``), the
collision checker of joint motions (``collision``), the sampled joint motion (``trajectory``) and
its configs (``params``)."""
