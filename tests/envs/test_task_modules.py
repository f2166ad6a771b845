"""Each task's spec holds only the env's facts: its tool settings (RL defaults, expert datasets,
demo) sit beside it in ``sonogym.tasks.<task>``, named by entry point, and load by task name;
the env package imports none of them."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import sonogym.envs
from sonogym.agents.task_defaults import TrainingDefaults, training_defaults
from sonogym.envs.registry import TASKS
from sonogym.envs.spec import load_entry_point
from sonogym.imitation.task_datasets import DatasetSpec, dataset_spec
from sonogym.tasks.demo import Demo, task_demo


def test_every_task_names_its_modules_beside_it():
    for name, spec in TASKS.items():
        for ref in (spec.agents, spec.demo, spec.dataset):
            assert ref is None or ref.startswith(f"sonogym.tasks.{name}."), ref
        assert isinstance(training_defaults(name), TrainingDefaults)
        assert isinstance(task_demo(spec.env_id), Demo)  # by Gymnasium id too
    assert isinstance(dataset_spec("navigation"), DatasetSpec)
    assert isinstance(dataset_spec("surgery"), DatasetSpec)
    with pytest.raises(ValueError, match=r"no expert datasets \(tasks with one: navigation, sur"):
        dataset_spec("reconstruction")
    with pytest.raises(ValueError, match="unknown task 'bogus'"):
        task_demo("bogus")


def test_a_bad_entry_point_names_the_task_and_field():
    spec = TASKS["navigation"]
    with pytest.raises(ValueError, match=r"task 'navigation' names no demo config"):
        load_entry_point("sonogym.tasks.navigation.demo", Demo, "navigation", "demo")
    with pytest.raises(TypeError, match=r"dataset:DATASET \(task 'navigation'\) is not a Demo"):
        load_entry_point(spec.dataset, Demo, "navigation", "demo")


def test_the_env_package_imports_nothing_from_the_tasks_package():
    root = Path(sonogym.envs.__file__).parent
    for path in root.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            bad = [n for n in names if n.startswith(("sonogym.tasks", "sonogym.imitation"))]
            assert not bad, f"{path.name} imports {bad}"
