"""What the monitor shows: the compositor and its overlays, the configured display target, screenshots."""

from .compositor import Compositor, Overlay
from .target import open_target, screen_file

__all__ = ["Compositor", "Overlay", "open_target", "screen_file"]
