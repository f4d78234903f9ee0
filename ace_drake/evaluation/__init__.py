"""Evaluation applications: rally controllers by name (``controllers``), one episode on the rally
diagram (``runner``), the main job's rallies (``rallies``) and the return-rate evaluation on
incoming shots (``evaluate``: ``ace-drake evaluate``)."""
