"""Artefact sidecars: how a file the project ships or writes was produced, in one JSON beside it.

Every artefact (a fitted ball model, identified joint dynamics, a camera calibration, a policy, a
learned racket residual) has a sidecar with the same name and the suffix ``.json``, written by
``write_sidecar``: the command line and date (``provenance``), the seed, the data files it was
made from with their sha256 (``data_file``), its figures, the sha256 of the artefact file itself
and whatever else its producer records. ``--json`` output goes through ``dumps`` too. JSON has no
NaN or infinity: ``dumps`` writes a number that is not finite as null, so every file is valid JSON.

Plain Python, at the bottom of the layers (docs/architecture.md), so that any layer can write one.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
import shlex
import sys
from pathlib import Path

_command_line: list[str] | None = None  # the ``ace-drake`` arguments being run, set by cli.main


def record_command_line(argv: list[str]) -> None:
    """Records the arguments of the ``ace-drake`` command being run, for ``provenance``."""
    global _command_line
    _command_line = list(argv)


def provenance() -> dict:
    """``{"command": ..., "date": ...}``: the command line that is running ("ace-drake <args>" under
    the CLI, else the Python command line) and today's date (ISO 8601)."""
    if _command_line is not None:
        command = "ace-drake " + " ".join(shlex.quote(argument) for argument in _command_line)
    else:
        command = " ".join(shlex.quote(argument) for argument in [Path(sys.executable).name, *sys.argv])
    return {"command": command, "date": datetime.date.today().isoformat()}


def sha256(path) -> str:
    """The sha256 of the file ``path``'s bytes, as 64 hex digits."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def data_file(path, **fields) -> dict:
    """A data file as a sidecar records it: ``{"file": its name, "sha256": ..., **fields}`` (e.g.
    how many rows were used)."""
    return {"file": Path(path).name, "sha256": sha256(path), **fields}


def finite_or_null(value):
    """``value`` as plain JSON data: NumPy and torch numbers and arrays (anything with ``tolist``)
    as Python ones, tuples as lists, and every float that is not finite as None, in nested dicts
    and lists."""
    if not isinstance(value, (str, bytes, dict, list, tuple)) and hasattr(value, "tolist"):
        value = value.tolist()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(item) for item in value]
    return value


def dumps(payload, indent: int | None = 2) -> str:
    """``payload`` as JSON text (``finite_or_null``: no NaN, NumPy values allowed); raises
    TypeError for anything else that JSON cannot hold."""
    return json.dumps(finite_or_null(payload), indent=indent, allow_nan=False)


def write_json(path, payload) -> dict:
    """Writes ``payload`` to ``path`` (``dumps``, a final newline) and returns what was written,
    read back (plain JSON data). The file is written beside it first and renamed over it, so that
    a crash leaves the old file or the new one, never a part."""
    text = dumps(payload)
    path = Path(path)
    partial = path.with_name(path.name + ".tmp")
    partial.write_text(text + "\n")
    os.replace(partial, path)
    return json.loads(text)


def sidecar_path(artefact) -> Path:
    """The sidecar of the artefact file ``artefact``: the same name with the suffix ``.json``."""
    return Path(artefact).with_suffix(".json")


def write_sidecar(artefact, *, seed: int | None = None, data=None, figures=None, command: str | None = None, **fields) -> dict:
    """Writes the sidecar of the artefact file ``artefact`` (already written) and returns its
    content as written. Keys: ``artefact`` (the file's name) and ``artefact_sha256``, ``command``
    and ``date`` (``provenance``; ``command`` replaces the recorded one), then ``seed``, ``data``
    (e.g. ``data_file(...)`` or a list of them) and ``figures`` when given, and ``fields`` in their
    order. Raises ValueError when the artefact file does not exist."""
    artefact = Path(artefact)
    if not artefact.is_file():
        raise ValueError(f"write_sidecar: the artefact {artefact} does not exist; write it first")
    if artefact.suffix == ".json":
        raise ValueError(f"write_sidecar: {artefact} ends in .json, the sidecar's own name")
    record = {"artefact": artefact.name, "artefact_sha256": sha256(artefact), **provenance()}
    if command is not None:
        record["command"] = command
    if seed is not None:
        record["seed"] = seed
    if data is not None:
        record["data"] = data
    if figures is not None:
        record["figures"] = figures
    record.update(fields)
    return write_json(sidecar_path(artefact), record)
