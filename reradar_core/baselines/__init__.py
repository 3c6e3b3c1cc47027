"""Published radar place-recognition baselines behind one interface (``PlaceRecognitionMethod``).

``make_method(name)`` builds one by name: the five baselines as their reference implementations
(``ringkey``, ``raplace``, ``radvlad``, ``resnet18-netvlad``, ``referee``; each module cites its reference
file and commit), the variants this project ran before (``raplace-nodc``, ``radvlad-half``; never the
reference rows), and ReRadar itself as ``ours`` / ``ours-<model>`` for every name in
``reradar_core.model.available_models()``; any ReRadar name with ``+far`` (``our-3-offroad-w05+far``) adds
ReRadar's far view for refused queries (``reradar_core.localization.far_view``; ours, not the paper's method), and
``+dense`` (``our-3-offroad-w05+dense``) the far view with its dense registration for queries both views refused
(``reradar_core.matching.dense``; ours too).
"""

from __future__ import annotations

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared, Retrieval
from reradar_core.errors import ConfigError

__all__ = ["PlaceRecognitionMethod", "Prepared", "Retrieval", "BASELINES", "VARIANTS", "make_method",
           "ours_model_names", "default_method_names"]

#: Baseline method names, in the paper's table order.
BASELINES = ("raplace", "radvlad", "resnet18-netvlad", "referee", "ringkey")
#: Separately named variants of baselines (not the reference implementations; run only when named).
VARIANTS = ("raplace-nodc", "radvlad-half")


def ours_model_names() -> list[str]:
    """Names of the shipped ReRadar models (``reradar_core.model.available_models()``; empty if none)."""
    try:
        from reradar_core.model import available_models
    except ImportError:
        return []
    return [str(m) for m in available_models()]


def default_method_names() -> list[str]:
    """Every baseline plus ReRadar with every shipped model (named by the model, e.g. ``our-3-boreas``)."""
    return list(BASELINES) + ours_model_names()


#: Suffix of a ReRadar method name that adds the far view (``our-3-offroad-w05+far``).
FAR_SUFFIX = "+far"
#: Suffix of a ReRadar method name that adds the far view and its dense registration (``our-3-offroad-w05+dense``).
DENSE_SUFFIX = "+dense"


def make_method(name: str) -> PlaceRecognitionMethod:
    """Build a method by name (see the module docstring).

    ``ours`` is ReRadar with the default model; a shipped model's name (``our-3-boreas``) or
    ``ours-<model>`` selects another; a path to a ``.pt`` weights file (JSON next to it) loads that file.

    Raises:
        ConfigError: unknown name; the message lists the valid ones.
    """
    key = name.strip().lower()
    if key == "ringkey":
        from reradar_core.baselines.ringkey import RingKey

        return RingKey()
    if key == "raplace":
        from reradar_core.baselines.raplace import RaPlace

        return RaPlace()
    if key == "raplace-nodc":
        from reradar_core.baselines.raplace import RaPlaceNoDC

        return RaPlaceNoDC()
    if key == "radvlad":
        from reradar_core.baselines.radvlad import RadVLAD

        return RadVLAD()
    if key == "radvlad-half":
        from reradar_core.baselines.radvlad import RadVLADHalf

        return RadVLADHalf()
    if key in ("resnet18-netvlad", "resnet18_netvlad", "netvlad"):
        from reradar_core.baselines.resnet_netvlad import ResNetNetVLAD

        return ResNetNetVLAD()
    if key == "referee":
        from reradar_core.baselines.referee import ReFeree

        return ReFeree()
    for suffix in (FAR_SUFFIX, DENSE_SUFFIX):  # ReRadar with its far view (``localization.far_view``) [and dense
        if not key.endswith(suffix):           # registration]: separately named rows
            continue
        from reradar_core.baselines.ours import Ours
        from reradar_core.localization.far_view import FarViewConfig

        near = make_method(name.strip()[: -len(suffix)])
        if not isinstance(near, Ours) or near.far_view is not None:
            what = near.name if not isinstance(near, Ours) else f"{near.name} (it has a far view already)"
            raise ConfigError(f"{suffix!r} applies to a ReRadar model without a far view, not to {what!r}")
        return Ours(near.extractor, near.localization, name=near.name + suffix, far_view=FarViewConfig(),
                    dense=suffix == DENSE_SUFFIX)
    known = ours_model_names()
    if name.strip().endswith(".pt"):  # a weights file (with its .json) outside the registry, e.g. a training run
        from pathlib import Path

        from reradar_core.baselines.ours import Ours

        path = Path(name.strip())
        if not path.is_file():
            raise ConfigError(f"model weights {path} not found")
        return Ours(str(path), name=path.stem)
    if key == "ours" or key in known or key.startswith("ours-"):
        from reradar_core.baselines.ours import Ours

        if key == "ours":
            return Ours("default", name="ours")
        model = name.strip()[len("ours-"):] if key.startswith("ours-") and key not in known else name.strip()
        if model not in known:
            raise ConfigError(f"unknown ReRadar model {model!r}; shipped models: {known or 'none'}")
        return Ours(model, name=model)
    raise ConfigError(f"unknown method {name!r}; choose from {default_method_names()}, the variants "
                      f"{list(VARIANTS)} or 'ours'")
