"""Validated profiles: every tunable number of the appliance lives in YAML under configs/."""

from .appliance import ApplianceProfile
from .case import CaseProfile
from .fluoroscope import FluoroscopeProfile
from .keymap import KeymapProfile
from .loading import KINDS, ApplianceConfig, load_appliance, load_profile, resolve, validate_paths
from .phantom import PhantomProfile
from .webcam import WebcamProfile
from .yamlfile import Problem, ProfileProblems

__all__ = ["ApplianceConfig", "ApplianceProfile", "CaseProfile", "FluoroscopeProfile", "KINDS", "KeymapProfile",
           "PhantomProfile", "Problem", "ProfileProblems", "WebcamProfile", "load_appliance", "load_profile",
           "resolve", "validate_paths"]
