"""The paper's evaluation protocols (§5 "Experiment setup"): which simulator and patients a run
trains on, and which it is tested on.

=============  =====================================  ========================================
protocol       training env options                   test env options (over the run's own)
=============  =====================================  ========================================
``idt``        patients = cohort training seeds       none: the run's simulator and patients
``odt-sim``    patients = training seeds,             simulator "learned", learned_nets (4,)
               simulator "learned", nets (0, 1, 2, 3)
``odt-patient``  patients = training seeds            patients = the held-out seed(s) (5,)
=============  =====================================  ========================================

Each protocol runs 100 trials from fixed seeds (``trials``, ``seed``) and reports mean ± std.
The table's ODT column is ``odt-sim`` for learned-simulator (LB) runs and ``odt-patient`` for
model-based (MB) runs, as in the paper's Table 1.

The test side checks the run it is given: ``odt-patient`` refuses a run whose training
patients include a held-out one, ``odt-sim`` a run not trained on the learned simulator or
trained with the test net. Protocol-driven training refuses held-out patients in any protocol.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from sonogym.evaluation.cohort import HELD_OUT_PATIENTS, TRAIN_PATIENTS, held_out, overlap

#: Learned-simulator nets for training and for the out-of-domain test (shipped net indices).
TRAIN_NETS: tuple[int, ...] = (0, 1, 2, 3)
TEST_NETS: tuple[int, ...] = (4,)
#: Env options a protocol sets; explicit overrides may not contradict them.
PROTOCOL_KEYS = ("patients", "simulator", "learned_nets")


class ProtocolError(ValueError):
    """A run or a training config does not fit the protocol."""


@dataclass(frozen=True)
class Protocol:
    """One evaluation protocol: training env options, test env overrides, trials and seed.

    ``train`` holds the env options training uses; ``test`` the options the test overrides on
    the run's own (empty: in-domain). ``column`` is the paper's table column (IDT or ODT)."""

    name: str
    title: str
    column: str
    train: dict[str, Any] = field(default_factory=dict)
    test: dict[str, Any] = field(default_factory=dict)
    trials: int = 100
    seed: int = 1000

    def train_env_kwargs(self, **explicit: Any) -> dict[str, Any]:
        """Training env options: the protocol's, then ``explicit`` ones (None: not given),
        checked (held-out patients are refused; see :meth:`check_train`)."""
        kw = dict(self.train)
        kw.update({k: v for k, v in explicit.items() if v is not None})
        if "patients" in kw:
            kw["patients"] = tuple(kw["patients"])
        self.check_train(kw)
        return kw

    def check_train(self, env_kwargs: dict[str, Any]) -> None:
        """Refuse training options that would leak the test domain into training."""
        leaked = overlap(env_kwargs.get("patients", ()), self._held_out())
        if leaked:
            raise ProtocolError(
                f"{self.name}: training patients {list(env_kwargs['patients'])} include "
                f"held-out patient(s) {list(leaked)}; held-out patients are test-only"
            )
        if self.name == "odt-sim":
            if not _draws_nets(env_kwargs.get("simulator")):
                raise ProtocolError(
                    f"odt-sim trains on the learned simulator, not {env_kwargs.get('simulator')!r}"
                )
            nets = tuple(env_kwargs.get("learned_nets", ()))
            if not nets or set(nets) & set(TEST_NETS):
                raise ProtocolError(
                    f"odt-sim trains on learned nets {list(TRAIN_NETS)} and tests on "
                    f"{list(TEST_NETS)}; got training nets {list(nets) or 'all (default)'}"
                )

    def test_env_overrides(self, run_env_kwargs: dict[str, Any]) -> dict[str, Any]:
        """The env overrides for testing a run trained with ``run_env_kwargs`` (its
        ``config.json`` ``task_config.env_kwargs``); raises :class:`ProtocolError` when the run
        does not fit the protocol."""
        if self.name == "odt-patient":
            seen = overlap(run_env_kwargs.get("patients", (0,)), self.test["patients"])
            if seen:
                raise ProtocolError(
                    f"odt-patient: the run was trained on patients "
                    f"{list(run_env_kwargs.get('patients', (0,)))}, which include the held-out "
                    f"test patient(s) {list(seen)}; train it on the cohort's training patients "
                    f"{list(TRAIN_PATIENTS)} (sonogym train --protocol odt-patient)"
                )
        if self.name == "odt-sim":
            sim = run_env_kwargs.get("simulator") or _simulator(None).name
            nets = run_env_kwargs.get("learned_nets")
            if not _draws_nets(sim):
                raise ProtocolError(
                    f"odt-sim tests a run trained on the learned simulator; this run used "
                    f"simulator {sim!r} (train with --protocol odt-sim)"
                )
            if nets is None or set(nets) & set(TEST_NETS):
                raise ProtocolError(
                    f"odt-sim: the run was trained on learned nets "
                    f"{list(nets) if nets is not None else 'all (default)'}, which include the "
                    f"test net(s) {list(TEST_NETS)}; train on {list(TRAIN_NETS)}"
                )
        return {k: (tuple(v) if isinstance(v, list) else v) for k, v in self.test.items()}

    def _held_out(self) -> tuple:
        return tuple(self.test.get("patients", HELD_OUT_PATIENTS))


def protocol(name: str, held_out_patients: int = 1) -> Protocol:
    """The protocol called ``name`` (``idt``, ``odt-sim``, ``odt-patient``).

    ``held_out_patients``: how many held-out phantoms ``odt-patient`` tests on (seeds 5, 6, ...).
    """
    if name == "idt":
        return Protocol(
            "idt", "in-domain test (same simulator and patients as training)", "IDT",
            train={"patients": TRAIN_PATIENTS},
        )  # fmt: skip
    if name == "odt-sim":
        return Protocol(
            "odt-sim",
            f"out-of-domain simulator (train on learned nets {list(TRAIN_NETS)}, "
            f"test on {list(TEST_NETS)})",
            "ODT",
            train={"patients": TRAIN_PATIENTS, "simulator": "learned", "learned_nets": TRAIN_NETS},
            test={"simulator": "learned", "learned_nets": TEST_NETS},
        )
    if name == "odt-patient":
        test = held_out(held_out_patients)
        return Protocol(
            "odt-patient",
            f"out-of-domain patient (train on patients {list(TRAIN_PATIENTS)}, "
            f"test on held-out {list(test)})",
            "ODT",
            train={"patients": TRAIN_PATIENTS},
            test={"patients": test},
        )
    raise ValueError(f"unknown protocol {name!r}; choose from {list(PROTOCOLS)}")


PROTOCOLS = ("idt", "odt-sim", "odt-patient")


def simulator_group(simulator: str | None) -> str:
    """The paper's simulator group of ``simulator`` (None: the envs' default), as the
    simulator registry declares it: "LB" (learning-based) or "MB" (model-based)."""
    return _simulator(simulator).group


def _draws_nets(simulator: str | None) -> bool:
    """Whether ``simulator`` (None: the envs' default) images with learned nets drawn from
    ``learned_nets``, which odt-sim splits into training and test nets."""
    return _simulator(simulator).draws_net


def _simulator(name: str | None):
    """The registry entry of simulator ``name`` (None: the envs' default)."""
    from sonogym.ultrasound.registry import DEFAULT_SIMULATOR, get_simulator

    return get_simulator(name or DEFAULT_SIMULATOR)


def protocol_train_kwargs(name: str, **explicit: Any) -> dict[str, Any]:
    """Training env options of protocol ``name`` with ``explicit`` overrides (None: not given),
    checked: ``sonogym train --protocol``."""
    return protocol(name).train_env_kwargs(**explicit)


def protocol_env_kwargs(
    name: str,
    env_kwargs: dict[str, Any],
    patients: tuple | None = None,
    simulator: str | None = None,
) -> dict[str, Any]:
    """``env_kwargs`` with the training env options of protocol ``name`` merged in, where the
    run's own ``patients``, ``simulator`` and ``env_kwargs["learned_nets"]`` (None / absent: not
    given) override the protocol's: ``sonogym train --protocol``."""
    own = {
        "patients": patients,
        "simulator": simulator,
        "learned_nets": env_kwargs.get("learned_nets"),
    }
    return {**env_kwargs, **protocol_train_kwargs(name, **own)}
