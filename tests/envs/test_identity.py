"""The benchmark identity: what it records, and which results may share a table."""

from __future__ import annotations

import pytest

from sonogym.anatomy.phantom import GENERATOR_VERSION
from sonogym.anatomy.variants import VARIANT_VERSION
from sonogym.envs.identity import IdentityMismatch, check_one_identity, identity, stamp
from sonogym.envs.registry import get_task
from sonogym.ultrasound.learned.inference import resolve_precision
from sonogym.ultrasound.learned.shipped import shipped_weights
from sonogym.ultrasound.simulator import MODEL_VERSIONS


def test_identity_records_generator_task_and_ultrasound():
    ident = identity("navigation", {"simulator": "reference"})
    assert ident == {
        "generator_version": GENERATOR_VERSION,
        "task": "navigation",
        "task_version": get_task("navigation").version,
        "ultrasound": {"model": "reference", "version": MODEL_VERSIONS["reference"]},
    }
    # the reference model's former name records its current one
    with pytest.warns(DeprecationWarning, match="'sonogym' is now called 'reference'"):
        assert identity("navigation", {"simulator": "sonogym"}) == ident
    # the config's defaults fill what the keywords leave out
    assert identity("surgery")["ultrasound"]["model"] == "physical"
    assert identity("navigation", {"patients": ("somewhere@3",)})["variant_version"] == (
        VARIANT_VERSION
    )


def test_navigation_task_version_counts_the_amended_goal():
    assert get_task("navigation").version == 2


def test_learned_identity_names_each_net_by_its_content():
    import hashlib

    ident = identity("navigation", {"simulator": "learned", "learned_nets": (0, 4)})
    us = ident["ultrasound"]
    assert us["model"] == "learned" and us["precision"] == resolve_precision("auto")
    assert list(us["nets"]) == ["net0", "net4"]
    digest = hashlib.sha256(shipped_weights(4).read_bytes()).hexdigest()[:16]
    assert us["nets"]["net4"] == digest
    assert us["nets"]["net0"] != us["nets"]["net4"]


def test_model_based_and_learned_rows_share_a_table_as_in_the_paper():
    mb = identity("surgery")
    idt = identity("surgery", {"simulator": "learned", "learned_nets": (0, 1, 2, 3)})
    odt = identity("surgery", {"simulator": "learned", "learned_nets": (4,)})
    table = check_one_identity({"mb": mb, "lb idt": idt, "lb odt": odt})
    assert [u["model"] for u in table["ultrasound"]] == ["physical", "learned"]
    assert list(table["ultrasound"][1]["nets"]) == ["net0", "net1", "net2", "net3", "net4"]
    line = stamp(table)
    assert f"generator v{GENERATOR_VERSION}" in line and "surgery task v1" in line
    assert "physical ultrasound v1" in line and "net4" in line


@pytest.mark.parametrize(
    "change, phrase",
    [
        ({"task_version": 1}, "task_version 1, not 2"),
        ({"generator_version": GENERATOR_VERSION - 1}, "generator_version"),
        ({"ultrasound": {"model": "physical", "version": 0}}, "physical ultrasound version 0"),
    ],
)
def test_a_table_refuses_a_result_of_another_identity_and_names_it(change, phrase):
    good = identity("navigation")
    with pytest.raises(IdentityMismatch, match="run-b") as e:
        check_one_identity({"run-a": good, "run-b": {**good, **change}})
    assert phrase in str(e.value) and "run-a" in str(e.value)


def test_a_table_refuses_a_learned_net_of_the_same_name_with_other_weights():
    a = identity("navigation", {"simulator": "learned", "learned_nets": (0,)})
    b = {**a, "ultrasound": {**a["ultrasound"], "nets": {"net0": "0" * 16}}}
    with pytest.raises(IdentityMismatch, match="learned net net0 with digest 0000"):
        check_one_identity({"a": a, "b": b})
    other = {"float32": "bfloat16", "bfloat16": "float32"}[a["ultrasound"]["precision"]]
    c = {**a, "ultrasound": {**a["ultrasound"], "precision": other}}
    with pytest.raises(IdentityMismatch, match=f"precision '{other}'"):
        check_one_identity({"a": a, "c": c})


def test_a_result_without_an_identity_is_named():
    with pytest.raises(IdentityMismatch, match="old-run: no benchmark identity"):
        check_one_identity({"new-run": identity("navigation"), "old-run": None})
