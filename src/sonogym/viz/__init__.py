"""Pictures of patients and images for people (matplotlib PNGs), above the simulator:
``preview`` (a patient's CT and labels with landmarks, for ``sonogym phantom``) and ``render``
(ultrasound at surface poses, ``sonogym image``). The simulation packages never import this."""
