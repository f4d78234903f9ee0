"""The artefact writer: provenance, sha256, sidecars, NaN-free JSON."""

import hashlib
import json

import numpy as np
import pytest

from ace_drake import artefacts


def test_sha256_is_the_files_digest(tmp_path):
    path = tmp_path / "data.csv"
    path.write_bytes(b"a,b\n1,2\n")
    assert artefacts.sha256(path) == hashlib.sha256(b"a,b\n1,2\n").hexdigest()
    assert artefacts.data_file(path, rows=1) == {"file": "data.csv", "sha256": hashlib.sha256(b"a,b\n1,2\n").hexdigest(), "rows": 1}


def test_provenance_records_the_ace_drake_command_line(monkeypatch):
    monkeypatch.setattr(artefacts, "_command_line", None)
    assert "command" in artefacts.provenance() and len(artefacts.provenance()["date"]) == 10
    artefacts.record_command_line(["physics-fit", "--holdout-player", "Elite B"])
    assert artefacts.provenance()["command"] == "ace-drake physics-fit --holdout-player 'Elite B'"


def test_json_has_no_nan_and_takes_numpy_values():
    payload = {"a": float("nan"), "b": [np.float64(1.5), np.inf], "c": np.arange(2), "d": (np.int64(3),), "e": {"f": -np.inf}}
    assert json.loads(artefacts.dumps(payload)) == {"a": None, "b": [1.5, None], "c": [0, 1], "d": [3], "e": {"f": None}}
    with pytest.raises(TypeError):
        artefacts.dumps({"a": object()})


def test_a_sidecar_records_its_artefact_provenance_data_and_figures(tmp_path, monkeypatch):
    monkeypatch.setattr(artefacts, "_command_line", ["sysid", "--log", "log.csv"])
    artefact = tmp_path / "model.yaml"
    artefact.write_text("a: 1\n")
    data = tmp_path / "log.csv"
    data.write_text("time\n0\n")
    written = artefacts.write_sidecar(artefact, seed=3, data=artefacts.data_file(data), figures={"error": float("nan")}, extra=[1, 2])
    stored = json.loads((tmp_path / "model.json").read_text())
    assert stored == written
    assert stored["artefact"] == "model.yaml" and stored["artefact_sha256"] == artefacts.sha256(artefact)
    assert stored["command"] == "ace-drake sysid --log log.csv" and stored["seed"] == 3 and stored["extra"] == [1, 2]
    assert stored["data"]["sha256"] == artefacts.sha256(data) and stored["figures"] == {"error": None}
    with pytest.raises(ValueError, match="does not exist"):
        artefacts.write_sidecar(tmp_path / "missing.pt")
