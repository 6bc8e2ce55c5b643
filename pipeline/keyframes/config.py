"""Task declarations (`params.yaml` `tasks.<name>`) as typed dataclasses, parsed and checked by
`task_parsing.py` (`load_tasks`).

A new task needs only its input, its ψ ranges (with ψ_raw) and its edit; everything else has a
default that fits the paper's tasks:

```yaml
tasks:
  my_jump:
    input: data/inputs/my_jump.npz
    edit: x                                  # or {mode: x, keyframes: [landing], sign: 1}
    psi: {raw: 1.0, easy: [[0.8, 1.2]], hard: [[1.2, 1.5]]}
```

Keyframe selectors (for `edit.keyframes` and `sparse_scale.keyframes`) are either a label or a
time in seconds. A label `landing` matches `landing` and the numbered `landing_1`, `landing_2`, ...
that automatic selection gives when an event happens more than once; `landing_2` matches only that
one. Everything is checked on loading, before any work; checks that need the motion (keyframe beyond the
clip's end, selector that matches nothing) run in `select_keyframes`, still before anything is
written.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pipeline.common.errors import PipelineInputError
from pipeline.motion.feet import MIN_FLIGHT_S
from pipeline.priors.push_prior import PushPriorConfig

EDIT_MODES = ("x", "z_apex", "z_hold", "y", "heading")
TERRAIN_KINDS = ("flat", "gap", "step")
SEMANTIC_LABELS = ("start", "takeoff", "apex", "landing", "hit", "end")
AUTO_EVENTS = ("takeoff", "apex", "landing", "hit")
# The edited keyframes when a task does not say: what the paper's tasks move.
DEFAULT_EDITED = {"x": ("landing",), "z_hold": ("landing",), "z_apex": ("apex",), "y": ("hit",),
                  "heading": ("hit",)}
# Edits that add up over several edited keyframes (triple jump's three landings, ...).
CUMULATIVE_MODES = ("x", "y", "heading")
LABEL_PATTERN = re.compile(r"^[a-z][a-z0-9]*(_[0-9]+)?$")

Selector = str | float  # a keyframe label (matches numbered ones too) or a time in seconds
Range = tuple[float, float]


def label_matches(selector: str, label: str) -> bool:
    """`landing` matches landing, landing_1, landing_2...; `landing_2` only itself."""
    if not label:
        return False
    return label == selector or re.fullmatch(re.escape(selector) + r"_[0-9]+", label) is not None


# ------------------------------------------------------------------------------------- parts
@dataclass(frozen=True)
class KeyframeSpec:
    time: float
    label: str = ""


@dataclass(frozen=True)
class KeyframesConfig:
    """`auto` finds semantic keyframes and fills the rest uniformly; `explicit` uses `listed`."""

    mode: str = "auto"  # auto | explicit
    listed: tuple[KeyframeSpec, ...] = ()  # explicit keyframes
    spacing: float = 0.3  # seconds between uniform keyframes
    first: float = 0.1  # time of the first uniform keyframe
    end_margin: float = 0.1  # no uniform keyframe closer than this to the clip's end
    min_gap: float = 0.12  # uniform keyframes closer than this to a semantic one are dropped
    events: tuple[str, ...] | None = None  # semantic events to find; None: by the edit (see select)
    overrides: dict[str, float] = field(default_factory=dict)  # label -> time replacing auto one
    extra: tuple[KeyframeSpec, ...] = ()  # added to the automatic ones
    min_flight: float = MIN_FLIGHT_S  # seconds without foot contact that count as a flight
    # `flights:` a count (the clip must hold that many flights, else an error lists those found) or the
    # flights listed by hand as [take-off, landing] times in seconds (then nothing is detected).
    flight_count: int | None = None
    flights: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class EditConfig:
    mode: str  # one of EDIT_MODES
    keyframes: tuple[Selector, ...]  # the edited keyframes
    sign: float = 1.0  # +1: ψ above ψ_raw moves forward/up/left; -1 (step down): the other way


@dataclass(frozen=True)
class PsiConfig:
    raw: float
    easy: tuple[Range, ...]
    hard: tuple[Range, ...]
    train: tuple[Range, ...]
    meaning: str = ""

    def as_ranges(self) -> dict[str, list[tuple[float, float]]]:
        return {k: [tuple(r) for r in getattr(self, k)] for k in ("train", "easy", "hard")}


@dataclass(frozen=True)
class TerrainConfig:
    """flat; gap (before each edited landing, the pit `depth` below); step (at the landing).

    Geometry anchors along the edit axis (`anchors`, metres from the clip's start) come from the
    motion (`terrain.resolve_terrain`) unless declared; `height` of a step is `reference` (the
    edited reference's own landing height: terrain and targets always agree) or `psi` (±ψ).
    """

    kind: str = "flat"
    # Gap and step edges stay this far from the reference's feet at takeoff and landing: the slack a
    # landing may fall short by. At 0.05 m a landing 6 cm short dropped the robot into the pit.
    margin: float = 0.15
    depth: float = 0.6  # pit floor below a gap
    height: str = "reference"
    anchors: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ClipWindow:
    """The seconds of the (retargeted) clip a task trains on: `clip: {start_s, end_s, lead_in_s}`.

    A long take trains on its interesting part (the jump, not the walk to it): every later stage sees
    only the window, and times elsewhere in the task (listed keyframes, flights) count from its start.
    `end_s` None: to the clip's end.
    """

    start_s: float = 0.0
    end_s: float | None = None
    # Seconds from the stance at rest to the window's first frame, prepended after the keyframes are chosen
    # (keyframes/lead_in.py): the task then starts where a standing robot is. 0: none.
    lead_in_s: float = 0.0
    # Where the chain hands the robot to the balance policy: this long after the last landing keyframe
    # (export/chain.py `handoff_phase`; the keyframes after it are judged by no one). None: at the window's end.
    handoff_after_landing_s: float | None = None

    def frames(self, fps: float, num_frames: int, task: str) -> tuple[int, int]:
        """The window as a slice [start, stop) of a clip with `num_frames` frames at `fps`."""
        duration = (num_frames - 1) / fps
        start = int(round(self.start_s * fps))
        stop = num_frames if self.end_s is None else int(round(self.end_s * fps)) + 1
        if self.end_s is not None and self.end_s > duration + 0.5 / fps:
            raise _err(task, "clip.end_s", f"{self.end_s} s is past the clip's end ({duration:.2f} s)")
        if stop - start < 2:
            raise _err(task, "clip.start_s", f"{self.start_s} s leaves fewer than 2 frames of the "
                       f"{duration:.2f} s clip")
        return start, stop


@dataclass(frozen=True)
class TaskConfig:
    name: str
    input: str
    edit: EditConfig
    psi: PsiConfig
    keyframes: KeyframesConfig = field(default_factory=KeyframesConfig)
    large_scale: float = 50.0
    large_scale_keyframes: tuple[Selector, ...] | None = None  # None: every semantic keyframe
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    num_samples: int = 64
    push_prior: PushPriorConfig = field(default_factory=PushPriorConfig)  # priors/push_prior.py
    clip: ClipWindow = field(default_factory=ClipWindow)

    # ------------------------------------------------------------------------------ helpers
    def input_path(self, root: str | Path = ".") -> Path:
        """The input, checked to exist (triple jump / badminton wait for a user's file)."""
        path = Path(root) / self.input
        if not path.is_file():
            raise PipelineInputError(f"task {self.name}", "input", f"no such file {path}")
        return path

    @staticmethod
    def from_dict(name: str, raw: dict) -> "TaskConfig":
        from pipeline.keyframes.task_parsing import parse_task

        return parse_task(name, raw)


def _err(name: str, fld: str, problem: str) -> PipelineInputError:
    return PipelineInputError(f"task {name}", fld, problem)
