"""Training presets (``--recipe``): the settings a paper states, and the choices made where it is silent.

``paper`` is the training section of the NSFlow paper; what it leaves open is listed in
:data:`PAPER_OPEN` with the choice made here, and the model card repeats it.
"""

from __future__ import annotations

from nsflow_ros.train.errors import TrainError

__all__ = ["PAPER", "PAPER_DATA", "PAPER_OPEN", "RECIPES", "recipe_defaults"]

PAPER: dict[str, object] = {
    "size": (640, 480),
    "points": 200,
    "iterations": 50,
    "window": 11,
    "lr": 1e-3,
    "batch": 1,
    "rgb": True,
    "d": 3,
    "width": 8,
    "head": "relu",
    "levels": 1,
}
"""The option values ``--recipe paper`` sets (argparse destinations); options given explicitly win."""

PAPER_DATA = "tartanair"
"""The ``--data`` kind ``--recipe paper`` needs."""

PAPER_OPEN: tuple[tuple[str, str], ...] = (
    ("training length: '1000 epochs' of an unstated epoch size, about a day on one RTX 4090",
     "--steps / --minutes as given; one epoch = --val-every steps"),
    ("'unrolled for up to 50 iterations' beside an implicit-differentiation backward",
     "50 = the LM iteration limit; backward implicit (--mode unroll to unroll them)"),
    ("perturbation std sigma of the initial flow", "ground truth + N(0, 2.5^2) px (--init-error)"),
    ("robust loss rho and its scale", "Cauchy, 1 px (--rho, --delta)"),
    ("illumination augmenter", "the project's perturb_pair (gain, offset, shading, gamma, noise)"),
    ("descriptor channels and head", "d = 3, ReLU: the paper's parameter count of 1,003 (1.01e-3 M)"),
    ("LM damping lambda^(0), nu, tolerance", "the project's training solver (fixed lambda^(0), eps 1e-3)"),
    ("pyramid levels in training", "one level (the window at full resolution)"),
    ("Harris or GFTT corners, their spacing", "GFTT (Shi-Tomasi), minimum distance 7 px"),
    ("TartanAir environments, Easy / Hard, train / test split",
     "every environment given except the held-out ones (--tartanair-val; default the last by name), "
     "Easy and Hard alike"),
    ("final model: 'lowest training loss'", "the last weights (training loss is one noisy pair per step)"),
)

RECIPES = {"paper": PAPER}


def recipe_defaults(name: str) -> dict[str, object]:
    """The option defaults a recipe sets; TrainError for an unknown recipe."""
    if name not in RECIPES:
        raise TrainError(f"unknown recipe {name!r}; known: {sorted(RECIPES)}")
    return dict(RECIPES[name])
