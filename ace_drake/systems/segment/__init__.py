"""The segment-stepped, batched rally systems (docs/architecture.md, *Segment stepping*).

Each system carries B environments (leading dimension of every port value and state) and acts
once per 32 ms control segment (``control.segment_timing``): at each tick every stateful system
computes what its environments do over the coming segment, vectorised over time and
environments, from feedthrough outputs of the systems it depends on, and stores its state at the
segment's end in one unrestricted update. No callback runs at 1 kHz. The continuous-time systems
one package up stay as the B = 1 reference (``RallyParams.stepping``).
"""
