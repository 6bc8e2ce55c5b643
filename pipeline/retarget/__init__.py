"""Retargeting: a `HumanMotion` to a G1 reference `Motion` (mink or placo IK from a task table),
with contacts, ground and anti-skate corrections, resampling, a quality report and a preview."""

from pipeline.retarget.config import RetargetConfig
from pipeline.retarget.core import retarget

__all__ = ["RetargetConfig", "retarget", "write_preview"]


def write_preview(*args, **kwargs):
    from pipeline.retarget.preview import write_preview as _write_preview

    return _write_preview(*args, **kwargs)
