"""How ``sonogym demo`` shows navigation (``TaskSpec.demo`` of ``sonogym.envs.navigation``):
the ultrasound image beside a top-down view of the back with the probe's path."""

from sonogym.envs import frames
from sonogym.tasks.demo import Demo

DEMO = Demo(image=frames.first_image, frame=frames.probe_frame, point=frames.probe_position)
