"""Where the shipped models are: $AVATAR_MOTOR_MODELS, else the checkout's models/ (a clone of the
repository), else the copy inside the installed package (a wheel built by `make wheel`)."""
from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def models_dir() -> Path:
    env = os.environ.get("AVATAR_MOTOR_MODELS")
    if env:
        return Path(env)
    checkout = _PACKAGE.parents[1] / "models"  # src/avatar_motor -> the repository's root
    if checkout.is_dir():
        return checkout
    return _PACKAGE / "_models"


MODELS = models_dir()
BASE_MODEL = MODELS / "primal-bandai"  # what adaptors and few-step samplers are trained on
# what the runtime runs unless told otherwise: the few-step generator (model card, "Few-step sampling")
FEW_STEP_MODEL = MODELS / "primal-bandai-emdm"
DEFAULT_MODEL = FEW_STEP_MODEL if (FEW_STEP_MODEL / "config.json").exists() else BASE_MODEL
