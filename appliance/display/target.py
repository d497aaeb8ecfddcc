"""Open the screen an appliance profile names: its framebuffer, or its file of explicit geometry."""

from __future__ import annotations

from pathlib import Path

from drivers.framebuffer import Display, open_display

from ..config import ApplianceProfile, resolve
from ..errors import FluorosimError


def screen_file(profile_path: str | Path, profile: ApplianceProfile) -> Path | None:
    """The file a 'file' display target writes (relative paths are under data_dir), else None."""
    d = profile.devices.display
    if d.target != "file":
        return None
    if not d.path:
        raise FluorosimError(f"{profile_path}: devices.display.path is needed when devices.display.target is 'file'")
    p = Path(d.path).expanduser()
    return p if p.is_absolute() else resolve(Path(profile_path), profile.data_dir) / p


def open_target(profile_path: str | Path, profile: ApplianceProfile, read_only: bool = False) -> Display:
    """The configured display; `read_only` to look at what another process shows without disturbing it."""
    d = profile.devices.display
    path = screen_file(profile_path, profile)
    try:
        if path is not None and not read_only:
            path.parent.mkdir(parents=True, exist_ok=True)
        return open_display(d.target, str(path) if path else None, d.width, d.height, d.bpp, read_only=read_only)
    except OSError as e:  # a DisplayError, or the screen file's folder that cannot be made
        raise FluorosimError(f"{e} (devices.display in {profile_path})") from None
