"""Generator registry: names accepted by ``datagen sample --gan``."""
from __future__ import annotations

from ..errors import SettingError, UserError
from ..gans.kinds import GAN_KINDS, KINDS
from .base import Generator

AVAILABLE = ("procedural", *KINDS)
GANS = KINDS


def make_generator(name: str, checkpoint: str | None = None, options: dict | None = None) -> Generator:
    """Build a generator by name. ``options`` are the generator's config fields."""
    options = dict(options or {})
    if name == "procedural":
        from .procedural import ProceduralConfig, ProceduralHeads

        if checkpoint:
            raise SettingError("the procedural generator takes no {checkpoint}")
        known = ProceduralConfig.__dataclass_fields__
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise UserError(f"unknown procedural option(s): {', '.join(unknown)}")
        for key in ("background", "defect_types", "defect_severity"):
            if isinstance(options.get(key), list):  # as JSON has it
                options[key] = tuple(options[key])
        return ProceduralHeads(ProceduralConfig(**options))
    if name in GAN_KINDS:
        from .gan import GANConfig, GANHeads

        if not checkpoint:
            raise SettingError(f"{{gan}} {name} needs {{checkpoint}} PATH: {GAN_KINDS[name].source}")
        unknown = sorted(set(options) - set(GANConfig.__dataclass_fields__))
        if unknown:
            raise UserError(f"unknown {name} option(s): {', '.join(unknown)}")
        return GANHeads(name, checkpoint, GANConfig(**options))
    raise UserError(f"unknown generator {name!r}; choose one of: {', '.join(AVAILABLE)}")
