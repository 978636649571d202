"""Modalities: one observation key with a kind (rgb, depth, lowdim) and a per-step shape."""

from __future__ import annotations

from dataclasses import asdict, dataclass

KINDS = ("rgb", "depth", "lowdim")


@dataclass(frozen=True)
class Modality:
    name: str
    kind: str
    shape: tuple[int, ...]

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"modality {self.name!r}: unknown kind {self.kind!r}; valid kinds: {', '.join(KINDS)}")
        shape = tuple(int(s) for s in self.shape)
        object.__setattr__(self, "shape", shape)
        expected = {"rgb": 3, "depth": 3, "lowdim": 1}[self.kind]
        if len(shape) != expected:
            raise ValueError(f"modality {self.name!r} ({self.kind}): shape {shape} should have {expected} dims")
        if self.kind == "rgb" and shape[-1] != 3:
            raise ValueError(f"modality {self.name!r}: rgb images are HxWx3, got {shape}")
        if self.kind == "depth" and shape[-1] != 1:
            raise ValueError(f"modality {self.name!r}: depth maps are HxWx1, got {shape}")

    @property
    def is_image(self) -> bool:
        return self.kind in ("rgb", "depth")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["shape"] = list(self.shape)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Modality":
        return cls(name=d["name"], kind=d["kind"], shape=tuple(d["shape"]))


def kind_of_key(key: str) -> str:
    """The kind of a robomimic observation key (``*_image`` rgb, ``*_depth`` depth, else lowdim)."""
    if key.endswith("_image"):
        return "rgb"
    if key.endswith("_depth"):
        return "depth"
    return "lowdim"


def paper_modalities(image_size: int = 84) -> list[Modality]:
    """The six modalities of the paper (section 4)."""
    hw = (image_size, image_size)
    return [
        Modality("agentview_image", "rgb", (*hw, 3)),
        Modality("robot0_eye_in_hand_image", "rgb", (*hw, 3)),
        Modality("agentview_depth", "depth", (*hw, 1)),
        Modality("robot0_eef_pos", "lowdim", (3,)),
        Modality("robot0_eef_quat", "lowdim", (4,)),
        Modality("robot0_gripper_qpos", "lowdim", (2,)),
    ]


def as_modalities(specs) -> list[Modality]:
    """Accept Modality objects or dicts (from a config or a checkpoint)."""
    out = [m if isinstance(m, Modality) else Modality.from_dict(dict(m)) for m in specs]
    names = [m.name for m in out]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate modality names in {names}")
    if not out:
        raise ValueError("a policy needs at least one modality")
    return out
