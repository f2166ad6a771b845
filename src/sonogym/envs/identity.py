"""The benchmark identity a result was made with, and the check that one table holds one.

A figure is comparable with another only when both were measured on the same patients, the
same task definition and the same imaging. ``identity(task, env_kwargs)`` records that for one
env configuration:

* ``generator_version``: the phantom generator's (``sonogym.anatomy.phantom``); its output for a
  seed is fixed by this version (the cohort fingerprint test holds it to that);
* ``variant_version``: the real-derived variants' generator (only when a ``DIR@N`` patient is
  used);
* ``task`` and ``task_version``: the task definition (reward, goal, regions, start
  distribution, episode length), bumped whenever any of them changes (``TaskSpec.version``);
* ``ultrasound``: the model-based model's name and version, or for the learned simulator each
  net's name and content digest and the precision it ran in;
* ``tissue`` (only when the probe's contact force compresses the tissue: ``contact_force`` > 0
  or ``force_action``): the compression model's version, the contact force (N) and whether
  a force action drives it. Results without it imaged static tissue, as the paper did.

Runs (``config.json``), evaluations (``eval*.json``), datasets (``meta/info.json``), reports and
plots carry it. ``check_one_identity`` refuses to put results of different identities in one
table: generator, variants, task and tissue must agree, and an ultrasound model that appears in
several results must be the same (model-based and learned rows may sit side by side, as in the
paper's Table 1).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: The file of a report's or plot's folder that records the benchmark identity of its results.
IDENTITY_FILE = "identity.json"


class IdentityMismatch(ValueError):
    """Results of different benchmark identities were put in one table; the message lists
    which result differs from the first, and in what."""


def ultrasound_identity(simulator: str, learned_nets=(), learned_precision: str = "auto"):
    """What images a result, as the simulator's registry entry records it
    (``sonogym.ultrasound.registry``): ``{"model": name, "version": n}`` for a model-based
    model (its current name, also when a former one was given); ``{"model": "learned", "nets":
    {name: digest}, "precision": ...}`` for the learned one, the precision as resolved on this
    machine ("auto": ``resolve_precision``)."""
    from sonogym.ultrasound.registry import SimulatorOptions
    from sonogym.ultrasound.registry import identity as simulator_identity

    nets = learned_nets if learned_nets is not None else ()
    options = SimulatorOptions(learned_nets=nets, learned_precision=learned_precision)
    return simulator_identity(simulator, options)


def identity(task: str, env_kwargs: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The benchmark identity of ``task``'s env built with ``env_kwargs`` (``make_vec``
    keywords; missing ones take the task config's defaults)."""
    from sonogym.anatomy.phantom import GENERATOR_VERSION
    from sonogym.anatomy.variants import VARIANT_VERSION
    from sonogym.envs.registry import get_task

    spec = get_task(task)
    kw = dict(env_kwargs or {})
    defaults = spec.config_cls()

    def get(key):
        return kw.get(key, getattr(defaults, key, None))

    out: dict[str, Any] = {"generator_version": GENERATOR_VERSION}
    patients = get("patients")
    patients = [patients] if isinstance(patients, int | str | Path) else list(patients or ())
    if any(isinstance(p, str) and "@" in p for p in patients):
        out["variant_version"] = VARIANT_VERSION
    out["task"] = spec.name
    out["task_version"] = spec.version
    out["ultrasound"] = ultrasound_identity(
        get("simulator"), get("learned_nets"), get("learned_precision")
    )
    tissue = tissue_identity(get("contact_force"), get("force_action"))
    if tissue is not None:
        out["tissue"] = tissue
    return out


def tissue_identity(contact_force, force_action) -> dict[str, Any] | None:
    """How the probe's contact force compressed the tissue (``sonogym.ultrasound.compression``),
    or None for static tissue (a contact force of 0 and no force action: the benchmark's)."""
    from sonogym.ultrasound.compression import COMPRESSION_VERSION

    force, action = float(contact_force or 0.0), bool(force_action)
    if force == 0.0 and not action:
        return None
    return {"version": COMPRESSION_VERSION, "contact_force_n": force, "force_action": action}


def differences(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    """What makes identity ``b`` incompatible with ``a`` in one table, one phrase each (empty:
    compatible). The ultrasound differs only where both use the same model."""
    return _definition_differences(a, b) + _ultrasound_differences(a, b)


def _definition_differences(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    keys = ("generator_version", "variant_version", "task", "task_version", "tissue")
    return [f"{k} {b.get(k)!r}, not {a.get(k)!r}" for k in keys if a.get(k) != b.get(k)]


def _ultrasound_differences(a: Mapping[str, Any], b: Mapping[str, Any]) -> list[str]:
    """Where ``a`` and ``b`` image with the same model but not the same way: another version
    or precision, or a net of the same name with other weights (different nets, as in-domain
    nets 0-3 against out-of-domain net 4, may share a table)."""
    ua, ub = a.get("ultrasound") or {}, b.get("ultrasound") or {}
    if ua.get("model") != ub.get("model") or ua == ub:
        return []
    model = ub.get("model")
    out = [
        f"{model} ultrasound {k} {ub.get(k)!r}, not {ua.get(k)!r}"
        for k in sorted((set(ua) | set(ub)) - {"nets"})
        if ua.get(k) != ub.get(k)
    ]
    na, nb = ua.get("nets") or {}, ub.get("nets") or {}
    same_name = [k for k in nb if k in na and na[k] != nb[k]]
    out += [f"{model} net {k} with digest {nb[k]}, not {na[k]}" for k in same_name]
    return out


def check_one_identity(results: Mapping[str, Mapping[str, Any] | None]) -> dict[str, Any]:
    """The identity shared by ``results`` (``{result name: its identity}``), checked: a
    result without one, or one that differs from the first (``differences``; its ultrasound
    from the first result with the same model), raises ``IdentityMismatch`` naming it.
    Returns the first result's identity with ``ultrasound`` replaced by the list of the
    distinct ultrasound identities, in order of appearance."""
    if not results:
        raise ValueError("no results to check")
    missing = [name for name, ident in results.items() if not ident]
    if missing:
        raise IdentityMismatch(
            f"{', '.join(missing)}: no benchmark identity recorded (made by an older sonogym); "
            "make it again with this version so that its figures can be compared"
        )
    (first_name, first), *_ = results.items()
    by_model: dict[Any, tuple[str, Mapping]] = {}  # model -> (first result using it, identity)
    problems = []
    for name, ident in results.items():
        model = (ident.get("ultrasound") or {}).get("model")
        ref_name, ref = by_model.setdefault(model, (name, ident))
        why = [f"{w} as in {first_name}" for w in _definition_differences(first, ident)]
        why += [f"{w} as in {ref_name}" for w in _ultrasound_differences(ref, ident)]
        if why:
            problems.append(f"{name} has {'; '.join(why)}")
    if problems:
        raise IdentityMismatch(
            "results of different benchmark identities cannot share a table: "
            + " | ".join(problems)
        )
    models = []
    for model, (_, ref) in by_model.items():
        us = dict(ref.get("ultrasound") or {})
        if "nets" in us:  # every net any result imaged with this model used
            nets = {}
            for ident in results.values():
                u = ident.get("ultrasound") or {}
                if u.get("model") == model:
                    nets.update(u.get("nets") or {})
            us["nets"] = dict(sorted(nets.items()))
        models.append(us)
    return {**{k: v for k, v in first.items() if k != "ultrasound"}, "ultrasound": models}


def stamp(ident: Mapping[str, Any]) -> str:
    """One line naming an identity (or a checked table's, ``check_one_identity``), as reports
    and plots print it."""
    us = ident.get("ultrasound")
    us = us if isinstance(us, list) else [us]
    parts = [f"generator v{ident.get('generator_version')}"]
    if "variant_version" in ident:
        parts.append(f"variants v{ident['variant_version']}")
    parts.append(f"{ident.get('task')} task v{ident.get('task_version')}")
    tissue = ident.get("tissue")
    if tissue:
        how = "force action" if tissue.get("force_action") else "fixed force"
        parts.append(f"tissue compressed v{tissue.get('version')} "
                     f"({tissue.get('contact_force_n'):g} N, {how})")  # fmt: skip
    for u in us:
        if not u:
            continue
        if "nets" in u:
            nets = ", ".join(f"{k} {v[:8]}" for k, v in u["nets"].items())
            parts.append(f"{u.get('model')} ultrasound ({nets}; {u.get('precision')})")
        else:
            parts.append(f"{u.get('model')} ultrasound v{u.get('version')}")
    return "benchmark identity: " + " · ".join(parts)
