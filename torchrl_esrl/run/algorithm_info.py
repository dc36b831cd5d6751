"""What a recipe says about the algorithm it runs, so that the run plumbing and the report need not
know any algorithm by name.

A recipe module declares ``ALGORITHMS``, one :class:`AlgorithmInfo` per name its runs can write
into ``summary.json`` (a recipe with variants, such as ``buffer.mode=shared``, lists each), and
passes the one a config runs to :func:`~torchrl_esrl.run.lifecycle.recipe_main`. The run prints
and plots with it; the report reads every recipe's ``ALGORITHMS`` (:func:`discover`) to label and
order its rows.
"""
from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class AlgorithmInfo:
    """name: ``summary.json``'s ``algorithm`` (the report groups runs by it); label: its display
    name; returned: the policy it returns, in words (``"ES mean"``); rank: its place among the
    report's rows (smaller first, then by label); td3_frames: what its ``td3_frames`` count, in
    words, where they are not a TD3 learner's own environment steps (empty: they are)."""

    name: str
    label: str
    returned: str
    rank: int = 100
    td3_frames: str = ""


def load_recipe(path: str | Path):
    """The recipe module at ``path``, imported (recipes are scripts, not a package): its
    ``ALGORITHMS``, ``holdings`` and ``train``; its ``main`` is built, not run."""
    path = Path(path)
    spec = importlib.util.spec_from_file_location(f"_recipe_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def training_recipes(recipes_dir: str | Path) -> dict[str, object]:
    """The recipes of ``recipes_dir`` that train, by file name: the modules whose ``main``
    :func:`~torchrl_esrl.run.lifecycle.recipe_main` built (it carries ``main.recipe``); scripts
    such as ``report.py`` are left out."""
    modules = {path.name: load_recipe(path) for path in sorted(Path(recipes_dir).glob("*.py"))}
    return {name: module for name, module in modules.items() if hasattr(getattr(module, "main", None), "recipe")}


def discover(recipes_dir: str | Path) -> dict[str, AlgorithmInfo]:
    """Every ``ALGORITHMS`` entry of the recipe modules in ``recipes_dir``, by name."""
    found: dict[str, AlgorithmInfo] = {}
    for path in sorted(Path(recipes_dir).glob("*.py")):
        for info in getattr(load_recipe(path), "ALGORITHMS", ()):
            found[info.name] = info
    return found
