"""Env options written as text (the command line, a sweep grid) -> ``make_vec`` keywords.

One parser per kind of text: ``parse_value`` (a number, true/false/none or a word),
``parse_patients`` (phantom seeds, seed ranges, subject folders and their variants),
``parse_learned_nets`` (shipped net indices and generator files) and ``parse_env_options``
(``KEY=VALUE`` items checked against the task's config). Bad text raises ``ValueError``
naming the item and the fix.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any


def parse_value(text: str) -> Any:
    """A grid or ``--env-option`` value: int, float, true/false/none, else the text."""
    text = text.strip()
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return {"true": True, "false": False, "none": None}.get(text.lower(), text)


def parse_patients(specs: list[str] | None) -> tuple[int | str, ...] | None:
    """Patients from the command line: an integer is a phantom seed, ``A-B`` (digits, A <= B)
    the seeds A..B inclusive, ``DIR@N`` variant N of the subject in folder DIR and ``DIR@A-B``
    its variants A..B (unless that is itself an existing path), anything else a subject folder;
    None when none were given. The shipped subject's checkout path
    (``tests/data/totalsegmentator_example``) names the package's copy where that path does
    not exist (``sonogym.package_data.data_path``). ``DIR@X`` with an existing folder DIR and
    an X that is no variant index is refused, naming the index."""
    if not specs:
        return None
    out: list[int | str] = []
    for p in specs:
        m = re.fullmatch(r"(\d+)-(\d+)", p.strip())
        v = None if Path(p).exists() else re.fullmatch(r"(.+)@(\d+)-(\d+)", p.strip())
        if m or v:
            lo, hi = (int(m.group(1)), int(m.group(2))) if m else (int(v[2]), int(v[3]))
            if lo > hi:
                raise ValueError(f"patient range {p!r}: {lo} > {hi}; write it low-high")
            if m:
                out.extend(range(lo, hi + 1))
            else:
                out.extend(f"{_subject_folder(v[1])}@{i}" for i in range(lo, hi + 1))
        else:
            out.append(int(p) if p.lstrip("-").isdigit() else _subject(p))
    return tuple(out)


def _subject(spec: str) -> str:
    """A subject folder or ``DIR@N`` from the command line, with the shipped subject's name
    resolved (``data_path``); a variant index that is not a number is refused."""
    if Path(spec).exists() or "@" not in spec:
        return _subject_folder(spec)
    folder, _, index = spec.rpartition("@")
    resolved = _subject_folder(folder)
    if not Path(resolved).is_dir():
        return spec  # not a variant of a folder here: the loader names the missing folder
    if not index.isdigit():
        raise ValueError(
            f"patient {spec!r}: {index!r} is not a variant index; write {folder}@N (variant N, "
            f"a whole number >= 0) or {folder}@A-B (variants A to B)"
        )
    return f"{resolved}@{index}"


def _subject_folder(folder: str) -> str:
    from sonogym.package_data import data_path

    return str(data_path(folder))


def parse_learned_nets(text: str) -> tuple[int | str, ...]:
    """``--learned-nets`` text: comma-separated shipped net indices (int) and/or generator.pt
    paths (str), e.g. "0,1,runs/lb/generator.pt"."""
    return tuple(int(v) if v.strip().isdigit() else v.strip() for v in text.split(","))


def parse_env_options(
    task: str,
    items: list[str] | None,
    own_flags: dict[str, str] | None = None,
    flag_values: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """``KEY=VALUE`` items -> env keyword arguments; values read as int, float,
    true/false/none or text (``parse_value``), comma-separated for an option whose default is
    a tuple. Names an unknown option, a malformed item, a repeated key, a non-number for a
    numeric option, anything but true/false for a switch, an option that has its own flag
    (``own_flags``: option -> the flag to use) and whatever the task's config refuses (NaN,
    inf or 1e309 for a number, 2.5 for an integer option: 2.0 is taken as 2).
    ``flag_values``: the env options other flags give (e.g. ``{"obs_mode": "us_scan"}`` from
    ``--obs-mode``), so that the config's checks across options see the run's values, not the
    defaults."""
    from sonogym.envs.registry import get_task

    own_flags = own_flags or {}
    config_cls = get_task(task).config_cls
    fields = sorted(f.name for f in dataclasses.fields(config_cls))
    defaults = config_cls()
    out: dict[str, Any] = {}
    given: dict[str, str] = {}  # the text as typed, for the messages
    for item in items or []:
        key, sep, value = item.partition("=")
        key = key.strip()
        given[key] = value.strip()
        if not sep or not key or not value.strip():
            raise ValueError(f"--env-option {item!r}: write KEY=VALUE, e.g. w5=50")
        if key in own_flags:
            raise ValueError(f"--env-option {key}: use {own_flags[key]} for this option")
        if key not in fields:
            raise ValueError(
                f"--env-option {key}: {task} has no such option; its options are {fields}"
            )
        if key in out:
            raise ValueError(f"--env-option {key} is given twice")
        default = getattr(defaults, key)
        if isinstance(default, tuple):  # e.g. action_scale=0.003,0.003,0.1
            out[key] = tuple(parse_value(v) for v in value.split(","))
            continue
        out[key] = parse_value(value)
        if isinstance(default, bool) and not isinstance(out[key], bool):
            raise ValueError(
                f"--env-option {key}={value}: {key} is a switch; write true or false "
                f"(default {str(default).lower()})"
            )
        number = (int, float)
        numeric = isinstance(out[key], number) and not isinstance(out[key], bool)
        if isinstance(default, number) and not isinstance(default, bool) and not numeric:
            raise ValueError(f"--env-option {key}={value}: expected a number (default {default!r})")
    base = dict(flag_values or {})
    try:  # the config's own checks (finite numbers, integers, ranges, options that go together)
        config = config_cls(**{**base, **out})
    except (TypeError, ValueError) as e:
        raise ValueError(_refusal(config_cls, base, out, given, e)) from None
    return {key: getattr(config, key) for key in out}  # 2.0 for an integer option: 2


def _refusal(config_cls, base: dict, out: dict, given: dict, error: Exception) -> str:
    """Why the config refuses ``out``: the first option it refuses with the others that it
    accepts alone (named with its text as typed), else the config's own message."""

    def refuses(kwargs: dict) -> Exception | None:
        try:
            config_cls(**kwargs)
        except (TypeError, ValueError) as e:
            return e
        return None

    bad = [k for k in out if refuses({**base, k: out[k]})]
    good = {k: v for k, v in out.items() if k not in bad}
    for key in bad:  # e.g. observe_tilt=true is fine with an obs_mode=us_scan given beside it
        e = refuses({**base, **good, key: out[key]})
        if e is not None:
            return f"--env-option {key}={given[key]}: {e}"
    return f"--env-option: {error}"
