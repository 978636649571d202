"""The noise suite moved to :mod:`nostra.noise` (it needs no simulator: observation noises also run
on recorded observations); this name stays for existing imports."""

from nostra.noise import (  # noqa: F401
    CAMERA_OF, DEPTH_KEYS, NOISES, PROPRIO_KEYS, RGB_KEYS, UNSEEN_TABLE_TEXTURE, WHOLE_EPISODE, Blackout, CamJitter,
    Injector, Mask, NoiseSchedule, ProprioZero, TableTexture, Unchanged, check_noise,
)
