"""Evaluation applications: rally controllers by name (``controllers``), the held-out evaluations
that choose the main job's (``heldout``), one episode on the rally diagram (``runner``), the
return-rate evaluation on incoming shots (``evaluate``: ``ace-drake evaluate``), matches under
ITTF rules (``match``, ``match_track``: ``ace-drake rally``) and the serve library (``serves``)."""
