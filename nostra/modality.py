"""The observation contract: a modality is one observation key with a kind (rgb, depth, lowdim)
and a per-step shape; ``sim_observations`` declares the modalities the simulator renders (the
paper's six), the one place that spells their keys. Everything else takes keys, kinds, cameras and
the image size from these objects: datasets and policies hold ``list[Modality]``, a checkpoint
stores them as plain dicts (``to_plain`` / ``as_modalities``, its only conversion), and evaluation
renders what a checkpoint's modalities say."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable

KINDS = ("rgb", "depth", "lowdim")
DEFAULT_IMAGE_SIZE = 84  # the paper's; what the simulator renders for a policy without images


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

    @property
    def camera(self) -> str | None:
        """The camera an image comes from, by robosuite's naming (``<camera>_image``, ``<camera>_depth``)."""
        if not self.is_image:
            return None
        return self.name.removesuffix("_image" if self.kind == "rgb" else "_depth")

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


# Keys other modules need by role, not as one of a set (spelled here only).
FRONT_IMAGE = "agentview_image"   # the third-person view: videos, a format's single "image"
WRIST_IMAGE = "robot0_eye_in_hand_image"  # the wrist camera: noise that occludes one camera
EEF_POS = "robot0_eef_pos"        # the end effector's position, recorded beside the actions


def sim_observations(image_size: int = DEFAULT_IMAGE_SIZE) -> "ObservationSpec":
    """What the simulator renders (``nostra.sim.env``): the paper's six modalities (section 4),
    images ``image_size`` pixels square, in robomimic's key names."""
    hw = (int(image_size), int(image_size))
    return ObservationSpec((
        Modality(FRONT_IMAGE, "rgb", (*hw, 3)),
        Modality("robot0_eye_in_hand_image", "rgb", (*hw, 3)),
        Modality("agentview_depth", "depth", (*hw, 1)),
        Modality(EEF_POS, "lowdim", (3,)),
        Modality("robot0_eef_quat", "lowdim", (4,)),
        Modality("robot0_gripper_qpos", "lowdim", (2,)),
    ))


def paper_modalities(image_size: int = DEFAULT_IMAGE_SIZE) -> list[Modality]:
    """The six modalities of the paper (section 4): what the simulator renders."""
    return list(sim_observations(image_size).modalities)


@dataclass(frozen=True)
class ObservationSpec:
    """An ordered set of modalities (diffusion_policy's ``shape_meta``), e.g. what a simulator renders."""

    modalities: tuple[Modality, ...]

    def __post_init__(self):
        object.__setattr__(self, "modalities", tuple(as_modalities(self.modalities)))
        image_size_of(self.modalities)  # one square size for every image

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.modalities)

    def keys_of(self, kind: str) -> tuple[str, ...]:
        if kind not in KINDS:
            raise ValueError(f"unknown kind {kind!r}; valid kinds: {', '.join(KINDS)}")
        return tuple(m.name for m in self.modalities if m.kind == kind)

    @property
    def rgb_keys(self) -> tuple[str, ...]:
        return self.keys_of("rgb")

    @property
    def depth_keys(self) -> tuple[str, ...]:
        return self.keys_of("depth")

    @property
    def lowdim_keys(self) -> tuple[str, ...]:
        return self.keys_of("lowdim")

    @property
    def cameras(self) -> tuple[str, ...]:
        """The cameras the images come from, in order (each once)."""
        return tuple(dict.fromkeys(m.camera for m in self.modalities if m.is_image))

    @property
    def depth_cameras(self) -> tuple[str, ...]:
        return tuple(m.camera for m in self.modalities if m.kind == "depth")

    @property
    def image_size(self) -> int | None:
        return image_size_of(self.modalities)

    def camera_of(self, key: str) -> str:
        m = self[key]
        if m.camera is None:
            raise ValueError(f"{key!r} is {m.kind}, not an image: it has no camera")
        return m.camera

    def select(self, keys: Iterable[str]) -> list[Modality]:
        """The modalities named ``keys``, in that order; unknown keys are refused, naming the valid ones."""
        keys = list(keys)
        by_name = {m.name: m for m in self.modalities}
        unknown = [k for k in keys if k not in by_name]
        if unknown:
            raise ValueError(f"unknown observation keys {unknown}; valid: {list(self.names)}")
        return [by_name[k] for k in keys]

    def __getitem__(self, key: str) -> Modality:
        return self.select([key])[0]


def image_size_of(modalities: Iterable[Modality]) -> int | None:
    """The side of the square images among ``modalities`` (None without images): a simulator
    renders every camera at one size, so a set with several sizes is refused."""
    sizes = sorted({m.shape[:2] for m in modalities if m.is_image})
    if not sizes:
        return None
    if len(sizes) > 1 or sizes[0][0] != sizes[0][1]:
        raise ValueError(f"images of one square size expected, got sizes {sizes}")
    return sizes[0][0]


def as_modalities(specs) -> list[Modality]:
    """Accept Modality objects or dicts (from a config or a checkpoint)."""
    out = [m if isinstance(m, Modality) else Modality.from_dict(dict(m)) for m in specs]
    names = [m.name for m in out]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate modality names in {names}")
    if not out:
        raise ValueError("a policy needs at least one modality")
    return out


def render_size(modalities: Iterable[Modality], requested: int | None = None) -> int:
    """The image size to render for a policy trained on ``modalities``: that of their images. A
    ``requested`` size (a config's) must agree, it never silently wins; for a policy without
    images it (else the default) is the size."""
    trained = image_size_of(modalities)
    if requested is not None and trained is not None and int(requested) != trained:
        raise ValueError(f"the policy was trained on {trained}x{trained} images, but {requested}x{requested} were "
                         "asked for; leave the image size unset (evaluate.image_size=null) to render the checkpoint's")
    return trained or int(requested or DEFAULT_IMAGE_SIZE)


def to_plain(modalities: Iterable[Modality]) -> list[dict]:
    """Modalities as plain dicts, what a checkpoint stores (Lightning's hparams must be plain);
    ``as_modalities`` reads them back."""
    return [m.to_dict() for m in as_modalities(modalities)]
