"""``python -m sonogym.learned_training data|train|ship|card|all --work DIR``: the shipped
learned-simulator nets' recipe (``recipe``) and model card (``model_card``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from sonogym.learned_training import recipe
from sonogym.learned_training.model_card import model_card


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=recipe.__doc__.split("\n")[0])
    ap.add_argument("stage", choices=["data", "train", "ship", "card", "all"])
    ap.add_argument("--work", type=Path, default=Path("runs/lb-recipe"))
    ap.add_argument("--nets", type=int, nargs="*", default=list(range(recipe.NUM_NETS)))
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    if a.stage in ("data", "all"):
        recipe.build_data(a.work, a.nets)
    if a.stage in ("train", "all"):
        recipe.train_all(a.work, a.nets)
    if a.stage in ("ship", "all"):
        for p in recipe.ship(a.work, nets=a.nets):
            print(p)
    if a.stage in ("card", "all"):
        card = model_card(a.work)
        (a.work / "model_card.json").write_text(json.dumps(card["json"], indent=1))
        (a.work / "model_card.md").write_text(card["markdown"])
        print(card["markdown"])


if __name__ == "__main__":
    main()
