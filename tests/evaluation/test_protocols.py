"""The cohort and the paper's protocols: which simulators and patients train and test use."""

from __future__ import annotations

import pytest

from sonogym.evaluation.cohort import (
    HELD_OUT_PATIENTS,
    LEARNED_DATA_SEEDS,
    POPULATION_PATIENTS,
    TRAIN_PATIENTS,
    held_out,
    overlap,
)
from sonogym.evaluation.protocols import (
    PROTOCOLS,
    ProtocolError,
    protocol,
    protocol_train_kwargs,
)


def test_cohort_is_disjoint_and_extends_without_overlap():
    assert TRAIN_PATIENTS == (0, 1, 2, 3, 4) and HELD_OUT_PATIENTS == (5,)
    assert held_out() == (5,) and held_out(3) == (5, 6, 7)
    assert not overlap(TRAIN_PATIENTS, held_out(50))
    with pytest.raises(ValueError, match="learned simulator"):
        held_out(2000)
    # the population's 32 training phantoms are apart from every held-out and data seed
    assert len(POPULATION_PATIENTS) == 32 and max(POPULATION_PATIENTS) < LEARNED_DATA_SEEDS
    assert not overlap(POPULATION_PATIENTS, held_out(95) + TRAIN_PATIENTS)
    with pytest.raises(ValueError, match="population"):
        held_out(96)
    assert overlap([0, "5"], [5]) == (5,)  # CLI digit strings name seeds


def test_idt_tests_on_the_runs_own_simulator_and_patients():
    p = protocol("idt")
    assert p.train_env_kwargs() == {"patients": TRAIN_PATIENTS}
    assert p.test_env_overrides({"patients": [0, 1, 2, 3, 4], "simulator": "reference"}) == {}
    assert (p.trials, p.seed, p.column) == (100, 1000, "IDT")


def test_odt_sim_trains_on_four_nets_and_tests_on_the_fifth():
    p = protocol("odt-sim")
    train = p.train_env_kwargs()
    assert train == {
        "patients": TRAIN_PATIENTS,
        "simulator": "learned",
        "learned_nets": (0, 1, 2, 3),
    }
    run_env = {"patients": [0, 1, 2, 3, 4], "simulator": "learned", "learned_nets": [0, 1, 2, 3]}
    assert p.test_env_overrides(run_env) == {"simulator": "learned", "learned_nets": (4,)}
    assert p.column == "ODT" and p.trials == 100
    # a run that saw net 4, or every net by default, or a model-based run is refused
    for bad in (
        {**run_env, "learned_nets": [0, 1, 2, 3, 4]},
        {"simulator": "learned"},
        {"patients": [0], "simulator": "physical"},
        {"patients": [0]},
    ):
        with pytest.raises(ProtocolError, match="odt-sim"):
            p.test_env_overrides(bad)
    with pytest.raises(ProtocolError, match="nets"):
        p.train_env_kwargs(learned_nets=(0, 1, 2, 3, 4))


def test_odt_patient_tests_on_held_out_patients_never_seen_in_training():
    p = protocol("odt-patient")
    assert p.train_env_kwargs() == {"patients": TRAIN_PATIENTS}
    assert p.test_env_overrides({"patients": [0, 1, 2, 3, 4]}) == {"patients": (5,)}
    assert protocol("odt-patient", held_out_patients=2).test["patients"] == (5, 6)
    with pytest.raises(ProtocolError, match=r"held-out test patient\(s\) \[5\]"):
        p.test_env_overrides({"patients": [0, 5]})
    with pytest.raises(ProtocolError, match="held-out"):
        p.test_env_overrides({"patients": ["5"]})
    # held-out patients never enter a protocol's training config
    for name in PROTOCOLS:
        for train in protocol(name).train, protocol(name).train_env_kwargs():
            assert not overlap(train.get("patients", ()), HELD_OUT_PATIENTS)
        with pytest.raises(ProtocolError, match="test-only"):
            protocol_train_kwargs(
                name, patients=(0, 5), simulator="learned" if name == "odt-sim" else None
            )
    # explicit options override the protocol's (and are still checked)
    assert protocol_train_kwargs("idt", patients=(0, 1), simulator="reference") == {
        "patients": (0, 1),
        "simulator": "reference",
    }
    with pytest.raises(ValueError, match="unknown protocol"):
        protocol("odt-noise")


def test_train_cli_applies_and_checks_the_protocol(monkeypatch):
    from typer.testing import CliRunner

    import sonogym.agents.train as train_mod
    from sonogym.cli import app

    seen = {}

    def fake_train(task, algo, **kw):
        seen.update(kw)
        raise SystemExit(0)

    monkeypatch.setattr(train_mod, "train", fake_train)
    res = CliRunner().invoke(app, ["train", "--task", "surgery", "--protocol", "odt-patient"])
    assert res.exit_code == 0, res.output
    assert seen["env_kwargs"]["patients"] == TRAIN_PATIENTS and seen["patients"] is None
    args = ["train", "--task", "surgery", "--protocol", "odt-patient", "--patients", "5"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code != 0 and "test-only" in res.output
    res = CliRunner().invoke(app, ["eval", "--run", "nowhere", "--protocol", "odt-noise"])
    assert res.exit_code != 0 and "unknown protocol" in res.output
