"""The active profiles, reloaded on SIGHUP, with the last good set kept when an edit is bad.

A technician's typo must not take the appliance down: `reload()` validates the whole set
again; if anything is wrong the appliance keeps running on what it had and `problem`
says why (shown as a banner until a good reload clears it).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

from ..config import ApplianceConfig, CaseProfile, ProfileProblems, load_appliance, load_profile, validate_paths
from ..errors import FluorosimError

log = logging.getLogger(__name__)


class ProfileKeeper:
    """Holds the last good `ApplianceConfig` loaded from `path`."""

    def __init__(self, path: Path, *, case: Path | None = None, data_dir: Path | None = None):
        self.path = Path(path)
        self.case_override = Path(case) if case is not None else None
        self.data_dir_override = Path(data_dir) if data_dir is not None else None
        # At start there is no last good set: a bad profile is the caller's one-line error.
        self.current: ApplianceConfig = self._load()
        self.problem: str | None = None
        self.generation = 1

    def _load(self) -> ApplianceConfig:
        config = load_appliance(self.path)
        # configs/../var reads as var in every message and path shown.
        data_dir = self.data_dir_override if self.data_dir_override is not None else config.data_dir
        config = dataclasses.replace(config, data_dir=Path(os.path.normpath(data_dir)))
        if self.case_override is None:
            return config
        # `fluorosim demo --case X`: the appliance as profiled, on another case.
        problems = validate_paths([self.case_override])
        if problems:
            raise ProfileProblems(problems)
        return dataclasses.replace(config, case=load_profile(self.case_override, CaseProfile),
                                   case_path=self.case_override)

    def reload(self) -> tuple[ApplianceConfig, bool]:
        """Load the profiles again; (config in force, whether it changed to a new valid set)."""
        try:
            new = self._load()
        except ProfileProblems as e:
            self.problem = str(e.problems[0]) + (f" (+{len(e.problems) - 1} more)" if len(e.problems) > 1 else "")
            for p in e.problems:
                log.error("reload refused: %s", p)
            return self.current, False
        except FluorosimError as e:
            self.problem = str(e)
            log.error("reload refused: %s", e)
            return self.current, False
        self.problem = None
        self.current = new
        self.generation += 1
        log.info("profiles reloaded from %s", self.path)
        return new, True
