"""How ``sonogym demo`` shows surgery (``TaskSpec.demo`` of ``sonogym.envs.surgery``): the
volume's elevation slices beside a side view of the corridor with the drill tip's path."""

from sonogym.envs import frames
from sonogym.tasks.demo import Demo

DEMO = Demo(image=frames.surgery_image, frame=frames.surgery_demo_frame, point=frames.drill_tip)
