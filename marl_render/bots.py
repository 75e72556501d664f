"""Old path of marl_render/populations/bots.py (issue 40): that very module (marl_render/populations/moved.py)."""
from marl_render.populations.moved import become

become(__name__, __spec__)
