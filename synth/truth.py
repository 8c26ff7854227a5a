"""What the synthetic world knows and ingest must never read: the answers' metadata.

Every dataset generator returns a :class:`DatasetTruth`; the world writes it to
``answers/<dataset>/truth.json``. Evaluation and the ground-truth checks of every later stage read it.
Arrays are stored as nested lists; all geometry is in canonical head space (metres, +y up, +z out of
the face, origin near the head centre), cameras in OpenCV convention.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np


@dataclass
class CameraTruth:
    """One camera as the renderer used it, in canonical head space for frame 0 of every subject."""

    name: str
    K: np.ndarray  # (3, 3) pixels of the written native image, pixel centre (u, v) at (u, v)
    w2c: np.ndarray  # (4, 4) canonical metres -> OpenCV camera
    dist: np.ndarray  # (5,) OpenCV k1, k2, p1, p2, k3 applied by the renderer
    width: int
    height: int


class RenderedRig(NamedTuple):
    """What a generator rendered a dataset with."""

    world_from_canonical: np.ndarray  # (4, 4) similarity: native world (native units) <- canonical metres
    cameras: list  # as the renderer used them: each with name, K, w2c, dist, width, height
    lights: Any  # point lights: positions (L, 3) canonical metres, intensities (L, 3) linear RGB
    colour_response: dict[str, np.ndarray]  # camera -> (3, 3) M with recorded_linear = M @ true_linear


@dataclass
class DatasetTruth:
    dataset: str  # "d1" .. "d4"
    layout: str  # "faceolat", "ava256", "stereo-rig", "nersemble"
    native_dir: str  # folder of the native dataset, relative to the world root
    world_from_canonical: np.ndarray  # (4, 4) similarity: native world (native units) <- canonical metres
    cameras: dict[str, CameraTruth]
    # (subject, frame) -> (4, 4) rigid motion of the head in canonical space for that frame
    # (identity where the head does not move); the renderer drew vertices @ head_pose.T.
    head_poses: dict[tuple[str, int], np.ndarray]
    # camera -> (3, 3) M with recorded_linear = M @ true_linear (before the codec's encoding).
    colour_response: dict[str, np.ndarray]
    light_positions: np.ndarray  # (L, 3) canonical metres
    light_intensities: np.ndarray  # (L, 3) linear RGB
    splits: dict[str, str]  # subject -> "train" | "val" | "test"
    extra: dict = field(default_factory=dict)  # dataset-specific facts (e.g. full-on frame indices)

    @classmethod
    def of_rig(
        cls,
        dataset: str,
        layout: str,
        native_dir: str,
        rig: RenderedRig,
        head_poses: dict,
        splits: dict,
        extra: dict,
    ) -> DatasetTruth:
        """The truth of a dataset rendered with ``rig``; ``head_poses`` as in the field of that name."""
        return cls(
            dataset=dataset,
            layout=layout,
            native_dir=native_dir,
            world_from_canonical=rig.world_from_canonical,
            cameras={c.name: CameraTruth(c.name, c.K, c.w2c, c.dist, c.width, c.height) for c in rig.cameras},
            head_poses=head_poses,
            colour_response=rig.colour_response,
            light_positions=rig.lights.positions,
            light_intensities=rig.lights.intensities,
            splits=dict(splits),
            extra=extra,
        )

    def to_json(self) -> dict:
        return {
            "dataset": self.dataset,
            "layout": self.layout,
            "native_dir": self.native_dir,
            "world_from_canonical": np.asarray(self.world_from_canonical).tolist(),
            "cameras": {
                name: {
                    "K": np.asarray(cam.K).tolist(),
                    "w2c": np.asarray(cam.w2c).tolist(),
                    "dist": np.asarray(cam.dist).tolist(),
                    "width": int(cam.width),
                    "height": int(cam.height),
                }
                for name, cam in self.cameras.items()
            },
            "head_poses": [
                {"subject": s, "frame": int(f), "pose": np.asarray(p).tolist()}
                for (s, f), p in sorted(self.head_poses.items())
            ],
            "colour_response": {name: np.asarray(m).tolist() for name, m in self.colour_response.items()},
            "light_positions": np.asarray(self.light_positions).tolist(),
            "light_intensities": np.asarray(self.light_intensities).tolist(),
            "splits": dict(sorted(self.splits.items())),
            "extra": self.extra,
        }

    @classmethod
    def from_json(cls, data: dict) -> DatasetTruth:
        return cls(
            dataset=data["dataset"],
            layout=data["layout"],
            native_dir=data["native_dir"],
            world_from_canonical=np.array(data["world_from_canonical"]),
            cameras={
                name: CameraTruth(
                    name=name,
                    K=np.array(c["K"]),
                    w2c=np.array(c["w2c"]),
                    dist=np.array(c["dist"]),
                    width=c["width"],
                    height=c["height"],
                )
                for name, c in data["cameras"].items()
            },
            head_poses={(e["subject"], e["frame"]): np.array(e["pose"]) for e in data["head_poses"]},
            colour_response={name: np.array(m) for name, m in data["colour_response"].items()},
            light_positions=np.array(data["light_positions"]).reshape(-1, 3),
            light_intensities=np.array(data["light_intensities"]).reshape(-1, 3),
            splits=data["splits"],
            extra=data.get("extra", {}),
        )

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_json(), indent=1, sort_keys=True))

    @classmethod
    def load(cls, path: Path) -> DatasetTruth:
        return cls.from_json(json.loads(Path(path).read_text()))
