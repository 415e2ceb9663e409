"""The model zoo (DESIGN §5): each served name, what it reads and how it is built. No torch here.

Models share trained parts: one visual encoder per modality (``rgb``, ``rgbd``) serves every model of that
modality, and ``egoposevr`` is ``hmd-rgbd``'s fusion net with KPO switched on in the runtime. The bundled
``egoposevr`` and ``hmd-rgbd`` serve several trainings of that net as one graph (a seed ensemble, made by
``export``); ``egoposevr-lite`` serves one net of that kind taught by them (``train --teachers``; the bundled one was
distilled from the two nets before their sitting fine-tune, then fine-tuned by them after it), for servers that
need sessions more than accuracy.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Final


@dataclasses.dataclass(frozen=True)
class ZooEntry:
    name: str
    description: str
    visual: str | None  # "rgb" | "rgbd" | None: which visual encoder
    fusion: dict[str, Any]  # FusionConfig overrides
    kpo: bool = False
    trained_as: str | None = None  # shares another entry's fusion weights

    @property
    def inputs(self) -> list[str]:
        return ["hmd"] + ({"rgb": ["rgb"], "rgbd": ["rgb", "depth"]}[self.visual] if self.visual else [])

    @property
    def fusion_name(self) -> str:
        """The trained fusion net this model runs."""
        return self.trained_as or self.name


ZOO: Final = {
    entry.name: entry
    for entry in (
        ZooEntry("hmd", "HMD stream only (EgoPoser-like baseline)", None, {"fusion": "none"}),
        ZooEntry("hmd-rgb1", "HMD + single-frame RGB keypoints", "rgb", {"visual_window": 1}),
        ZooEntry("hmd-rgb", "HMD + multi-frame RGB keypoints", "rgb", {}),
        ZooEntry("hmd-rgbd", "HMD + multi-frame RGB-D keypoints", "rgbd", {}),
        ZooEntry(
            "egoposevr", "HMD + multi-frame RGB-D + KPO (the full system)", "rgbd", {}, True, "hmd-rgbd"
        ),
        ZooEntry("hmd-rgbd-concat", "ablation: fusion by concatenation", "rgbd", {"fusion": "concat"}),
        ZooEntry(
            "egoposevr-lite",
            "the full system on one net taught by egoposevr's nets: half the fusion work per sample",
            "rgbd",
            {},
            True,
            "hmd-rgbd",
        ),
    )
}


def resolve(names: str) -> list[str]:
    """``"all"`` or a comma-separated list -> known names, in zoo order. Raises ValueError on unknown ones."""
    wanted = list(ZOO) if names.strip() in ("", "all") else [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in wanted if n not in ZOO]
    if unknown:
        raise ValueError(f"unknown model(s) {', '.join(unknown)}; known: {', '.join(ZOO)}")
    return [n for n in ZOO if n in wanted]


def fusion_names(names: list[str]) -> list[str]:
    """The fusion nets the named models run, each once, in the names' order (models may share one)."""
    return list(dict.fromkeys(ZOO[n].fusion_name for n in names))
