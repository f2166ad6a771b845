"""Training of the learned (pix2pix) ultrasound simulator, outside the simulation packages:
paired CT/US data (``data``), ``sonogym lb-train`` (``train``), the shipped nets' recipe
(``recipe``, ``python -m sonogym.learned_training``) and their model card (``model_card``).
The simulator side (networks, histogram matching, checkpoint loading, ``LearnedSimulator``)
lives in ``sonogym.ultrasound.learned``. See docs/learned.md."""
