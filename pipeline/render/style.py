"""The look of every picture the pipeline draws: a checker floor, a sky, a key light with a shadow, and the
task's obstacle in a colour that stands out (the gap's pit, the raised side of a step).

Applied to the visual scene only (`build_spec(visual=True)`), after the terrain is added: physics never sees
it. The floor's checker squares are 0.5 m so distances can be read off a video. The far edge of the terrain
boxes fades into the sky (fog, set by the renderer), so the pit below them does not draw a band across the horizon.
"""

from __future__ import annotations

import mujoco
import numpy as np

SKY_TOP, SKY_HORIZON = [0.42, 0.60, 0.82], [0.90, 0.93, 0.97]
FLOOR_LIGHT, FLOOR_DARK = [0.86, 0.87, 0.88], [0.68, 0.70, 0.73]
OBSTACLE_LIGHT, OBSTACLE_DARK = [0.96, 0.58, 0.24], [0.86, 0.45, 0.16]
CHECKER_SQUARE_M = 0.5

FLOOR_MATERIAL, OBSTACLE_MATERIAL = "render_floor", "render_obstacle"
FLOOR_GEOMS = ("ground",)
PIT_GEOMS = ("terrain_pit",)
TERRAIN_PREFIX = "terrain_box"
RAISED_M = 0.02  # a terrain box whose top is this far above the lowest is the step's raised side


def _checker(spec: mujoco.MjSpec, name: str, light, dark) -> None:
    spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=light, rgb2=dark, width=256, height=256)
    # texuniform: the texture repeats per metre of surface; one repeat holds two squares a side
    material = spec.add_material(name=name, texuniform=True, texrepeat=[1.0 / (2 * CHECKER_SQUARE_M)] * 2,
                                 reflectance=0.0, specular=0.1)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = name


def style_scene(spec: mujoco.MjSpec) -> None:
    spec.add_texture(name="render_sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, rgb1=SKY_TOP, rgb2=SKY_HORIZON,
                     width=256, height=1536)
    _checker(spec, FLOOR_MATERIAL, FLOOR_LIGHT, FLOOR_DARK)
    _checker(spec, OBSTACLE_MATERIAL, OBSTACLE_LIGHT, OBSTACLE_DARK)
    for geom in spec.geoms:
        if geom.name in FLOOR_GEOMS or geom.name.startswith(TERRAIN_PREFIX):
            geom.material, geom.rgba = FLOOR_MATERIAL, [1.0, 1.0, 1.0, 1.0]
        elif geom.name in PIT_GEOMS:
            geom.material, geom.rgba = OBSTACLE_MATERIAL, [1.0, 1.0, 1.0, 1.0]

    # the headlight shines from the camera, which grazes the floor: a sun from above lights the floor
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.3, 0.3, 0.3]
    spec.visual.headlight.specular = [0.1, 0.1, 0.1]
    spec.worldbody.add_light(name="render_sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=[0, 0, 10],
                             dir=[0.2, 0.3, -1.0], diffuse=[0.3, 0.3, 0.3], specular=[0.0, 0.0, 0.0],
                             castshadow=False)
    # a spot light above the robot on the camera's side that follows its centre of mass, casting its shadow:
    # a narrow cone keeps the shadow map sharp (a light over the whole terrain smears it into specks)
    spec.worldbody.add_light(name="render_key", mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM, pos=[0.6, -1.8, 4.5],
                             dir=[-0.12, 0.38, -1.0], cutoff=30.0, exponent=2.0, diffuse=[0.4, 0.4, 0.4],
                             specular=[0.2, 0.2, 0.2], castshadow=True)
    spec.visual.rgba.fog = SKY_HORIZON + [1.0]
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, 1280)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, 720)
    spec.visual.quality.shadowsize = 2048


def mark_raised_terrain(model: mujoco.MjModel) -> int:
    """Paints the terrain boxes raised above the lowest one (a step's high side, laid out for this ψ) in the
    obstacle colour; returns how many. Only drawing fields change."""
    boxes = [i for i in range(model.ngeom) if (model.geom(i).name or "").startswith(TERRAIN_PREFIX)]
    material = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, OBSTACLE_MATERIAL)
    if not boxes or material < 0:
        return 0
    tops = np.array([model.geom_pos[i, 2] + model.geom_size[i, 2] for i in boxes])
    raised = [g for g, top in zip(boxes, tops) if top > tops.min() + RAISED_M]
    for g in raised:
        model.geom_matid[g] = material
    return len(raised)
