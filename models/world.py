"""The truth world: a MuJoCo lander over a lunar heightfield, with a camera.

Ports:
    Input: thrust [N] and body torque (3,) [N m] held over ``step`` calls.
    Output (truth, for ``bench/`` only): :class:`TruthState`, the truth
        signals the sensor models corrupt (specific force, angular rate,
        altimeter range), camera images and depth, camera pose, contacts.
    Rate: physics at ``physics_dt_ns``; rendering on request.

The landing frame L is MuJoCo's world frame: origin at the landing target on
the surface (the terrain is shifted so its height there is 0), x east,
y north, z up. Gravity is ``-gravity_mps2 * z``.

Never silent: after every physics chunk, MuJoCo's warning counters for bad
qacc/qpos/qvel are checked and :class:`PhysicsDivergedError` is raised
(MuJoCo would otherwise reset the state and carry on).
"""

from __future__ import annotations

import ctypes
import logging
import math
import weakref
from dataclasses import dataclass

import cv2
import numpy as np

from models.gl import ensure_gl_backend

ensure_gl_backend()
import mujoco  # noqa: E402  (the GL backend must be chosen first)

from models.actuators import PropulsionModel, PropulsionOutput  # noqa: E402
from models.camera import R_MJCAM_C, CameraConfig, intrinsics, offscreen_samples  # noqa: E402
from models.render_context import CameraRenderer, CulledGeoms, arrays_digest, gl_function, visual_digest  # noqa: E402
from models.lander import (  # noqa: E402
    CONTACT_SOLREF,
    FOOTPAD_NAMES,
    HIDDEN_TILE_GEOM_GROUP,
    PATCH_GEOM_GROUP,
    TANK_MASS_FLOOR_KG,
    TERRAIN_GEOM_GROUP,
    TERRAIN_TILE_GEOM_GROUP,
    LanderConfig,
    actuator_mjcf,
    lander_mjcf,
    sensor_mjcf,
)
from models.terrain import Terrain  # noqa: E402
from models.sun import SunConfig  # noqa: E402,F401  (the scenario's type; re-exported)

NS_PER_S = 1_000_000_000
# Terrain -> digest of the texture pixels a world writes from it (see World._texture_key).
_TEXTURE_KEYS: "weakref.WeakKeyDictionary[Terrain, bytes]" = weakref.WeakKeyDictionary()
logger = logging.getLogger(__name__)
# MuJoCo's default warning handler appends to MUJOCO_LOG.TXT in the working
# directory; route its warnings to logging instead. Divergence is still caught
# through the warning counters below.
mujoco.set_mju_user_warning(lambda msg: logger.warning("MuJoCo: %s", msg))

# Thickness of the heightfield's solid base below its lowest point [m].
HFIELD_BASE_M = 5.0
# The landing-site texture patch is drawn this far above the coplanar terrain so
# it wins the depth test; far below any physical or optical tolerance [m].
PATCH_LIFT_M = 0.005
PATCH_BASE_M = 0.01
# Light: MuJoCo clamps lit colour at 1, so the sun's diffuse intensity is set
# to map flat ground at the sun's elevation to this fraction of the albedo.
FLAT_GROUND_EXPOSURE = 0.9
SHADOW_MAP_PX = 2048  # side of the shadow depth map when shadows are on [px]
# What mjv_updateScene draws a frame from (the kinematics mj_forward leaves in mjData): the poses
# of the bodies, geoms, sites, the camera and the lights, and the joint positions.
VISUAL_STATE_FIELDS = ("qpos", "xpos", "xmat", "xquat", "xipos", "ximat", "geom_xpos", "geom_xmat",
                       "site_xpos", "site_xmat", "cam_xpos", "cam_xmat", "light_xpos", "light_xdir",
                       "subtree_com")
AMBIENT_LIGHT = 0.04  # earthshine/scatter floor, keeps shadows from going fully black
MAX_SUN_DIFFUSE = 4.0

_DIVERGENCE_WARNINGS = (
    (mujoco.mjtWarning.mjWARN_BADQACC, "bad qacc (NaN/Inf acceleration)"),
    (mujoco.mjtWarning.mjWARN_BADQPOS, "bad qpos (NaN/Inf or huge position)"),
    (mujoco.mjtWarning.mjWARN_BADQVEL, "bad qvel (NaN/Inf or huge velocity)"),
)


class PhysicsDivergedError(RuntimeError):
    """The physics state became invalid; the run must not continue."""


# World.step's check on the velocity: a change beyond this factor times what the engine and gravity can give,
# plus a floor for rounding, is a broken integration [-], [m/s].
VELOCITY_JUMP_FACTOR = 3.0
VELOCITY_JUMP_FLOOR_MPS = 0.05
CONTACT_FREE_MARGIN_M = 10.0  # the check holds only this far above where any part of the lander could touch [m]


@dataclass(frozen=True)
class TruthState:
    """Truth state of the lander (for ``bench/`` scoring only).

    Attributes:
        t_ns: Simulation time [ns].
        r_BL_L: Body origin relative to the landing target, in L (3,) [m].
        v_BL_L: Body origin velocity in L (3,) [m/s].
        q_LB: Attitude, scalar-first (4,), body to L.
        omega_B: Angular rate of B in B (3,) [rad/s].
        mass_kg: Total mass [kg].
        propellant_kg: Propellant left [kg].
    """

    t_ns: int
    r_BL_L: np.ndarray
    v_BL_L: np.ndarray
    q_LB: np.ndarray
    omega_B: np.ndarray
    mass_kg: float
    propellant_kg: float


def hfield_z_range_m(height_m: np.ndarray) -> float:
    """A heightfield's vertical size in the MJCF (``size`` z) for these heights [m]: their span, at
    least 1 mm. One function for the terrain's and the patch's heightfields and the terrain's tiles,
    whose vertices must be the heightfield's own (NumPy's ``ptp`` of float32 heights rounds to float32)."""
    return max(float(np.ptp(height_m)), 1e-3)


TERRAIN_TILE_CELLS = 16  # grid cells along a side of a terrain tile (8 x 8 tiles on the default 129-post grid)


@dataclass(frozen=True)
class TerrainTiles:
    """The camera's drawing of a texture-shaded terrain: its heightfield cut into visual-only mesh tiles.

    MuJoCo draws a heightfield whole, every triangle of it, wherever the camera looks, and on a CPU
    renderer (llvmpipe) the triangles out of view still cost their vertex work. Cut into tiles, the
    ones wholly outside the camera's view are left out of each frame (:class:`CameraRenderer`): a
    256² frame of the default terrain took 4.1 ms at 30 m and 10.7 ms at 500 m drawn from the
    heightfield, 2.6 and 6.4 ms from the tiles in view (2 and 30 of 64; one process, interleaved).

    The tiles are the heightfield's own triangles: MuJoCo's vertices (``mjr_uploadHField``'s float32
    formula, from the heights as ``World`` writes them), split along the same diagonal, with the
    texture coordinates MuJoCo generates for a heightfield (one object-linear map over its whole
    extent). A frame drawn from them differs from the heightfield's by rasterisation rounding only
    (tests/test_terrain_tiles.py: at most 1 DN, on under 1 % of the pixels). Only for a
    texture-shaded terrain, whose material is unlit: a mesh's smoothed normals would otherwise
    shade it differently from the heightfield's flat triangles.

    Attributes:
        assets: MJCF ``<mesh>`` elements, one per tile.
        geoms: MJCF ``<geom>`` elements, group ``TERRAIN_TILE_GEOM_GROUP``, no contacts.
        corners_L: (K, 8, 3) corners of each tile's bounding box in L [m] (the mesh geoms sit at the origin).
    """

    assets: str
    geoms: str
    corners_L: np.ndarray


def terrain_tiles(terrain: Terrain, cells: int = TERRAIN_TILE_CELLS) -> TerrainTiles:
    """The terrain heightfield of :func:`world_mjcf` as mesh tiles of ``cells`` x ``cells`` grid cells."""
    f32 = np.float32
    h = terrain.height_m.astype(np.float64)
    n_rows, n_cols = h.shape
    half = f32(terrain.size_m / 2.0)
    z_range = hfield_z_range_m(terrain.height_m)  # the heightfield's size z, as world_mjcf writes it
    base = float(h.min())
    # As mjr_uploadHField draws them: float32 grid coordinates, heights data * size_z on the geom at `base`.
    data = ((h - base) / z_range).astype(f32)
    x = half * (np.arange(n_cols, dtype=f32) / f32(0.5 * (n_cols - 1)) - f32(1.0))
    y = half * (np.arange(n_rows, dtype=f32) / f32(0.5 * (n_rows - 1)) - f32(1.0))
    z = (data * f32(z_range)).astype(np.float64) + base
    # MuJoCo's texture generation for a 2-D texture on a heightfield (render_gl3.c, settexture).
    s = (f32(0.5) / half) * x - f32(0.5)
    t = -(f32(0.5) / half) * y - f32(0.5)
    assets, geoms, corners = [], [], []
    for r0 in range(0, n_rows - 1, cells):
        for c0 in range(0, n_cols - 1, cells):
            r1, c1 = min(r0 + cells, n_rows - 1), min(c0 + cells, n_cols - 1)
            nr, nc = r1 - r0 + 1, c1 - c0 + 1
            X, Y = np.meshgrid(x[c0:c1 + 1].astype(np.float64), y[r0:r1 + 1].astype(np.float64))
            Z = z[r0:r1 + 1, c0:c1 + 1]
            S, T = np.meshgrid(s[c0:c1 + 1].astype(np.float64), t[r0:r1 + 1].astype(np.float64))
            # Cell (i, j) with corners a = (i, j), b = (i, j+1), c = (i+1, j), d = (i+1, j+1): the
            # heightfield's triangles (c, a, d) and (a, b, d), counter-clockwise seen from above.
            a = (np.arange(nr - 1)[:, None] * nc + np.arange(nc - 1)[None, :]).ravel()
            b, c, d = a + 1, a + nc, a + nc + 1
            faces = np.column_stack([c, a, d, a, b, d]).ravel()
            name = f"terrain_tile{len(corners)}"
            vertex = " ".join(map(repr, np.column_stack([X.ravel(), Y.ravel(), Z.ravel()]).ravel().tolist()))
            texcoord = " ".join(map(repr, np.column_stack([S.ravel(), T.ravel()]).ravel().tolist()))
            assets.append(f'<mesh name="{name}" vertex="{vertex}" texcoord="{texcoord}" '
                          f'face="{" ".join(map(str, faces.tolist()))}" inertia="shell"/>')
            geoms.append(f'<geom name="{name}" type="mesh" mesh="{name}" material="regolith" '
                         f'group="{TERRAIN_TILE_GEOM_GROUP}" contype="0" conaffinity="0"/>')
            lo = (X.min(), Y.min(), Z.min())
            hi = (X.max(), Y.max(), Z.max())
            corners.append([(xx, yy, zz) for xx in (lo[0], hi[0]) for yy in (lo[1], hi[1]) for zz in (lo[2], hi[2])])
    return TerrainTiles("\n    ".join(assets), "\n    ".join(geoms), np.array(corners, np.float64))


def world_mjcf(terrain: Terrain, lander: LanderConfig, camera: CameraConfig, sun: SunConfig,
               physics_dt_s: float, gravity_mps2: float, tiles: TerrainTiles | None = None) -> str:
    """Assemble the MJCF of the whole world (heights and texture are written later).

    ``tiles``: the camera's drawing of the terrain (:func:`terrain_tiles`), added as visual-only geoms.
    """
    n_rows, n_cols = terrain.height_m.shape
    tex_rows, tex_cols = terrain.albedo.shape
    half = terrain.size_m / 2.0
    z_range = hfield_z_range_m(terrain.height_m)
    sun_dir = sun.direction_L()
    diffuse = min(FLAT_GROUND_EXPOSURE / sun_dir[2], MAX_SUN_DIFFUSE)
    ambient = AMBIENT_LIGHT
    # The terrain's material: lit by the sun, or (a texture that carries the whole relief's shading)
    # unlit, drawn at the brightness the sun gives flat ground (no light at all: nothing else is in view).
    emission = 0.0
    if terrain.relief_shaded:
        emission, diffuse, ambient = FLAT_GROUND_EXPOSURE + AMBIENT_LIGHT, 0.0, 0.0
    shadow = "true" if sun.shadows else "false"
    # Without shadows, no shadow map: MuJoCo would still allocate it in every GL context.
    shadow_px = SHADOW_MAP_PX if sun.shadows else 0
    patch_assets = patch_geom = ""
    if terrain.patch is not None:
        pt = terrain.patch
        p_half = pt.size_m / 2.0
        p_range = hfield_z_range_m(pt.height_m)
        p_rows, p_cols = pt.albedo.shape
        patch_assets = f"""
    <hfield name="patch" nrow="{pt.height_m.shape[0]}" ncol="{pt.height_m.shape[1]}" size="{p_half} {p_half} {p_range} {PATCH_BASE_M}"/>
    <texture name="patch_albedo" type="2d" builtin="flat" width="{p_cols}" height="{p_rows}" rgb1="0.5 0.5 0.5"/>
    <material name="patch_regolith" texture="patch_albedo" specular="0" shininess="0" reflectance="0" emission="{emission}" rgba="1 1 1 1"/>"""
        # Visual only (no contacts): coplanar with the terrain, lifted a hair to win the depth test,
        # and listed first so it is drawn first: the terrain's fragments under it then fail the
        # early depth test instead of being shaded and overdrawn (halves the fill cost there).
        patch_geom = f"""
    <geom name="terrain_patch" type="hfield" hfield="patch" material="patch_regolith" group="{PATCH_GEOM_GROUP}"
          pos="0 0 {float(pt.height_m.min()) + PATCH_LIFT_M}" contype="0" conaffinity="0"/>"""
    offw = max(camera.width_px, 64)
    offh = max(camera.height_px, 64)
    return f"""
<mujoco model="landbench">
  <option timestep="{physics_dt_s}" gravity="0 0 {-gravity_mps2}" integrator="implicitfast"/>
  <visual>
    <global offwidth="{offw}" offheight="{offh}"/>
    <headlight active="0" ambient="0 0 0" diffuse="0 0 0" specular="0 0 0"/>
    <quality shadowsize="{shadow_px}" offsamples="{offscreen_samples(camera, terrain.relief_shaded)}"/>
  </visual>
  <asset>
    <hfield name="terrain" nrow="{n_rows}" ncol="{n_cols}" size="{half} {half} {z_range} {HFIELD_BASE_M}"/>
    <texture name="albedo" type="2d" builtin="flat" width="{tex_cols}" height="{tex_rows}" rgb1="0.5 0.5 0.5"/>
    <material name="regolith" texture="albedo" specular="0" shininess="0" reflectance="0" emission="{emission}" rgba="1 1 1 1"/>{patch_assets}
    {tiles.assets if tiles is not None else ""}
  </asset>
  <worldbody>
    <light name="sun" directional="true" castshadow="{shadow}" pos="0 0 1000"
           dir="{-sun_dir[0]} {-sun_dir[1]} {-sun_dir[2]}"
           diffuse="{diffuse} {diffuse} {diffuse}" ambient="{ambient} {ambient} {ambient}"
           specular="0 0 0"/>
{patch_geom}
    {tiles.geoms if tiles is not None else ""}
    <geom name="terrain" type="hfield" hfield="terrain" material="regolith" group="{TERRAIN_GEOM_GROUP}"
          pos="0 0 {float(terrain.height_m.min())}" contype="0" conaffinity="1" friction="{lander.friction} 0.005 0.0001" solref="{CONTACT_SOLREF}"/>
    {lander_mjcf(lander, camera.fovy_deg)}
  </worldbody>
  <actuator>{actuator_mjcf(lander)}
  </actuator>
  <sensor>{sensor_mjcf()}
  </sensor>
</mujoco>"""


GL_VENDOR, GL_RENDERER, GL_VERSION = 0x1F00, 0x1F01, 0x1F02  # glGetString's names (OpenGL 1.0)


class World:
    """MuJoCo truth world with propulsion, truth signals and rendering.

    Args:
        terrain: The terrain (geometry grid and albedo texture).
        lander: Lander configuration.
        camera: Camera configuration (size, FOV; used for rendering).
        sun: Sun direction and shadows.
        physics_dt_ns: Physics step [ns].
        gravity_mps2: Surface gravity magnitude [m/s^2].
        realism: "ideal" (the default here, for library use): the lander's idealised actuators
            (:meth:`LanderConfig.ideal`), whatever its engine-dynamics, misalignment, centre-of-mass
            and RCS settings; "realistic": the lander as configured (a scenario's default).
    """

    def __init__(self, terrain: Terrain, lander: LanderConfig, camera: CameraConfig, sun: SunConfig,
                 physics_dt_ns: int, gravity_mps2: float = 1.62, realism: str = "ideal"):
        if realism not in ("ideal", "realistic"):
            raise ValueError(f"realism = {realism!r}; allowed: 'ideal' or 'realistic'")
        if realism == "ideal":
            lander = lander.ideal()
        elif lander.rcs.mode == "pwm" and lander.rcs.pwm_period_ns % int(physics_dt_ns):
            raise ValueError(f"lander.rcs.pwm_period_ns = {lander.rcs.pwm_period_ns} is not a whole multiple of "
                             f"the physics step {int(physics_dt_ns)} ns; allowed: multiples of it")
        self.realism = realism
        self.terrain = terrain
        self.lander_cfg = lander
        self.camera_cfg = camera
        self.physics_dt_ns = int(physics_dt_ns)
        self.dt_s = self.physics_dt_ns / NS_PER_S
        self.gravity_mps2 = gravity_mps2
        # A texture-shaded terrain is drawn by the camera from tiles, culled to its view (TerrainTiles).
        tiles = terrain_tiles(terrain) if terrain.relief_shaded else None
        self.model = mujoco.MjModel.from_xml_string(
            world_mjcf(terrain, lander, camera, sun, self.dt_s, gravity_mps2, tiles)
        )
        self._write_terrain(terrain)
        # Above this height of the body origin no part of the lander can touch the ground (its highest point
        # plus the lander's largest extent and a margin): World.step's velocity check holds there.
        reach_m = math.hypot(max(lander.leg_radius_m, *lander.body_half_extents_m),
                             lander.leg_drop_m + lander.footpad_radius_m + max(lander.body_half_extents_m))
        self._contact_free_z_m = float(np.max(terrain.height_m)) + reach_m + CONTACT_FREE_MARGIN_M
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._body_lander = m.body("lander").id
        self._body_tank = m.body("tank").id
        self._cam = m.camera("nadir").id
        self._site_alt = m.site("altimeter").id
        self._geom_terrain = m.geom("terrain").id
        self._foot_geoms = np.array([m.geom(n).id for n in FOOTPAD_NAMES])
        self._geom_hull = m.geom("hull").id
        self._lander_geoms = np.flatnonzero(m.geom_bodyid == self._body_lander)
        self._act_engine = m.actuator("engine").id
        self._act_rcs = np.array([m.actuator(n).id for n in ("rcs_x", "rcs_y", "rcs_z")])
        self._sens_acc = slice(m.sensor_adr[m.sensor("imu_acc").id], m.sensor_adr[m.sensor("imu_acc").id] + 3)
        self._sens_gyro = slice(m.sensor_adr[m.sensor("imu_gyro").id], m.sensor_adr[m.sensor("imu_gyro").id] + 3)
        self._ray_groups = np.zeros(mujoco.mjNGROUP, np.uint8)
        self._ray_groups[TERRAIN_GEOM_GROUP] = 1
        self._ray_groups[PATCH_GEOM_GROUP] = 1  # the altimeter sees the surface that is drawn
        self._ray_geomid = np.zeros(1, np.int32)
        self.propulsion = PropulsionModel(lander)
        self.K = intrinsics(camera)
        self._renderer: CameraRenderer | None = None
        self._camera_tiles = None if tiles is None else CulledGeoms(
            geom_ids=np.array([m.geom(f"terrain_tile{k}").id for k in range(len(tiles.corners_L))]),
            corners=tiles.corners_L, group=TERRAIN_TILE_GEOM_GROUP, hidden_group=HIDDEN_TILE_GEOM_GROUP,
            replaces_group=TERRAIN_GEOM_GROUP)
        self._depth_renderer: mujoco.Renderer | None = None
        # Per-physics-step indices and live views into MjData (allocated once; mj_resetData keeps them).
        self._i_engine = int(self._act_engine)
        self._i_rcs_xyz = tuple(int(i) for i in self._act_rcs)
        self._i_acc_xyz = tuple(range(self._sens_acc.start, self._sens_acc.stop))
        self._i_divergence = tuple(int(w) for w, _ in _DIVERGENCE_WARNINGS)
        self._ctrl = self.data.ctrl
        self._sensordata = self.data.sensordata
        self._qvel = self.data.qvel
        self._warning_number = self.data.warning.number  # MuJoCo's warning counters, (mjNWARNING,)
        self._step_count = 0
        # Kept as three floats each, summed step by step in the same order as the (3,) arrays were.
        self._imu_sum = [0.0, 0.0, 0.0]  # integrating accelerometer: sum of the steps' specific forces [m/s^2]
        self._gyro_sum = [0.0, 0.0, 0.0]  # integrating gyro: sum of the steps' integrated body rates [rad/s]
        self._imu_steps = 0
        self._fault_torque_B: np.ndarray | None = None
        self._set_clip_planes()
        mujoco.mj_forward(self.model, self.data)

    # ----------------------------------------------------------------- build
    def _write_terrain(self, terrain: Terrain) -> None:
        """Write heights (normalised to [0, 1] of each hfield's z range) and the textures."""
        self._write_hfield("terrain", terrain.height_m)
        self._write_texture("albedo", terrain.albedo)
        if terrain.patch is not None:
            self._write_hfield("patch", terrain.patch.height_m)
            self._write_texture("patch_albedo", terrain.patch.albedo)

    def _write_hfield(self, name: str, height_m: np.ndarray) -> None:
        m = self.model
        hid = m.hfield(name).id
        h = height_m.astype(np.float64)
        adr, count = m.hfield_adr[hid], m.hfield_nrow[hid] * m.hfield_ncol[hid]
        m.hfield_data[adr:adr + count] = ((h - h.min()) / m.hfield_size[hid, 2]).ravel()

    def _write_texture(self, name: str, albedo: np.ndarray) -> None:
        m = self.model
        tid = m.texture(name).id
        nch = int(m.tex_nchannel[tid])
        # MuJoCo maps texture row 0 to the north (+y) edge; terrain rows run south to north. The grey
        # value goes to every channel, written in place into a (rows, cols, nch) view of tex_data
        # (for RGB by OpenCV's grey-to-RGB conversion: a tenth of np.repeat's time on 4096^2).
        rows, cols = albedo.shape
        adr = int(m.tex_adr[tid])
        view = m.tex_data[adr:adr + rows * cols * nch].reshape(rows, cols, nch)
        north_up = cv2.flip(np.ascontiguousarray(albedo, dtype=np.uint8), 0)
        if nch != 3 or cv2.cvtColor(north_up, cv2.COLOR_GRAY2RGB, dst=view) is not view:
            view[...] = north_up[..., None]

    def _texture_key(self) -> bytes:
        """Digest of the pixels ``_write_terrain`` wrote into the model's textures: its albedo
        arrays (21 MB for the default terrain, not the 63 MB of RGB), once per terrain object
        (a terrain's arrays are read-only)."""
        key = _TEXTURE_KEYS.get(self.terrain)
        if key is None:
            patch = self.terrain.patch
            key = arrays_digest([self.terrain.albedo] + ([patch.albedo] if patch is not None else []))
            _TEXTURE_KEYS[self.terrain] = key
        return key

    def render_digest(self) -> bytes:
        """Digest of everything the camera's renderer uploads from this world (textures, heightfields,
        meshes, the visual block) and of the frame size (:func:`models.render_context.visual_digest`): two
        worlds with the same digest draw the same frame from the same visual state."""
        cfg = self.camera_cfg
        return visual_digest(self.model, cfg.width_px, cfg.height_px, self._texture_key())

    @property
    def clip_far_m(self) -> float:
        """The camera's far clip plane [m]: 4 x the terrain's size."""
        return 4.0 * self.terrain.size_m

    def _set_clip_planes(self) -> None:
        """Near/far planes in metres (MuJoCo stores them relative to the model extent)."""
        extent = float(self.model.stat.extent)
        self.model.vis.map.znear = self.camera_cfg.near_m / extent
        self.model.vis.map.zfar = self.clip_far_m / extent

    # ----------------------------------------------------------------- state
    @property
    def t_ns(self) -> int:
        return self._step_count * self.physics_dt_ns

    def reset(self, r_BL_L: np.ndarray, v_BL_L: np.ndarray, q_LB: np.ndarray, omega_B: np.ndarray) -> None:
        """Place the lander (body origin) and zero time.

        Args:
            r_BL_L: Position in L (3,) [m].
            v_BL_L: Velocity in L (3,) [m/s].
            q_LB: Attitude, scalar-first (4,).
            omega_B: Body rate in B (3,) [rad/s].
        """
        mujoco.mj_resetData(self.model, self.data)
        self.propulsion = PropulsionModel(self.lander_cfg)
        self._set_propellant(self.propulsion.propellant_kg)
        q = np.asarray(q_LB, float)
        self.data.qpos[0:3] = r_BL_L
        self.data.qpos[3:7] = q / np.linalg.norm(q)
        self.data.qvel[0:3] = v_BL_L
        self.data.qvel[3:6] = omega_B
        self._step_count = 0
        self._imu_sum = [0.0, 0.0, 0.0]
        self._gyro_sum = [0.0, 0.0, 0.0]
        self._imu_steps = 0
        mujoco.mj_forward(self.model, self.data)

    def set_pose(self, r_BL_L: np.ndarray, q_LB: np.ndarray) -> None:
        """Place the lander kinematically (at rest), keeping time and propellant.

        For rendering fixed viewpoints and replaying trajectories; physics
        state other than the pose is zeroed.
        """
        q = np.asarray(q_LB, float)
        self.data.qpos[0:3] = r_BL_L
        self.data.qpos[3:7] = q / np.linalg.norm(q)
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def _set_propellant(self, propellant_kg: float) -> None:
        mass = max(propellant_kg, TANK_MASS_FLOOR_KG)
        self.model.body_mass[self._body_tank] = mass
        self.model.body_inertia[self._body_tank] = self.lander_cfg.tank_inertia_kgm2(mass)

    def truth(self) -> TruthState:
        """Current truth state (copies)."""
        d = self.data
        prop = self.propulsion.propellant_kg
        return TruthState(
            t_ns=self.t_ns,
            r_BL_L=d.qpos[0:3].copy(),
            v_BL_L=d.qvel[0:3].copy(),
            q_LB=d.qpos[3:7].copy(),
            omega_B=d.qvel[3:6].copy(),
            mass_kg=self.lander_cfg.dry_mass_kg + prop,
            propellant_kg=prop,
        )

    # ----------------------------------------------------------------- step
    def step(self, n_steps: int, thrust_cmd_N: float = 0.0, torque_cmd_B_Nm: np.ndarray | None = None) -> PropulsionOutput:
        """Advance ``n_steps`` physics steps with the commands held.

        Raises:
            PhysicsDivergedError: MuJoCo flagged a bad qacc, qpos or qvel, or the velocity changed by more than
                the engine and gravity can change it with nothing touching the ground
                (:meth:`_check_velocity_change`).
        """
        d = self.data
        v0 = (d.qvel.item(0), d.qvel.item(1), d.qvel.item(2))
        w0 = d.qvel.item(3) ** 2 + d.qvel.item(4) ** 2 + d.qvel.item(5) ** 2
        z0 = d.qpos.item(2)
        torque = np.zeros(3) if torque_cmd_B_Nm is None else torque_cmd_B_Nm
        try:
            out = self._step_each(n_steps, thrust_cmd_N, torque) if not self.propulsion.instant else \
                self._step_instant(n_steps, thrust_cmd_N, torque)
        except PhysicsDivergedError as exc:  # MuJoCo's warning: say what the state was, and what to look at
            raise PhysicsDivergedError(f"{exc} {self._divergence_hint(v0, w0, z0)}") from None
        self._check_velocity_change(v0, w0, z0, n_steps)
        return out

    def _divergence_hint(self, v0: tuple[float, float, float], w0_sq: float, z0_m: float) -> str:
        """The state at the start of the interval MuJoCo diverged in (velocity ``v0`` [m/s], squared body rate
        ``w0_sq`` [rad^2/s^2], height ``z0_m`` [m]), and where to look: a physics step too large for the contact
        dynamics only where a contact could act (see :meth:`_check_velocity_change`)."""
        state = (f"At the start of that interval the lander was at z = {z0_m:.6g} m, moving at "
                 f"{math.sqrt(sum(v * v for v in v0)):.3g} m/s and turning at {math.degrees(math.sqrt(w0_sq)):.3g} deg/s.")
        if z0_m <= self._contact_free_z_m:
            return (f"{state} Near the ground a physics step too large for the contact dynamics is the usual cause: "
                    f"reduce sim.physics_dt_ns (now {self.physics_dt_ns}).")
        return (f"{state} No part of it could touch the ground, so contact is not the cause and a smaller "
                f"sim.physics_dt_ns (now {self.physics_dt_ns}) is unlikely to help: look at that state, the "
                f"commands before it and the mass properties (lander.*).")

    def _check_velocity_change(self, v0: tuple[float, float, float], w0_sq: float, z0_m: float, n_steps: int) -> None:
        """Where no part of the lander can touch the ground (the body origin above the terrain's highest point by
        the lander's reach and CONTACT_FREE_MARGIN_M, at both ends of the interval), the velocity can change over
        ``n_steps`` by at most what the strongest thrust the engine can deliver and gravity give, plus the body
        origin's turn about an offset centre of mass; a change of VELOCITY_JUMP_FACTOR times that is a broken
        integration MuJoCo does not flag (seen: a tumbling lander near an empty tank gaining 350 m/s in 20 ms
        while its accelerometer read 1 m/s^2). ``v0``, ``w0_sq`` and ``z0_m``: the velocity [m/s], the squared
        body rate [rad^2/s^2] and the height [m] before the interval.

        Raises:
            PhysicsDivergedError: Naming the change, the bound and the time.
        """
        d = self.data
        if d.ncon or min(z0_m, d.qpos.item(2)) <= self._contact_free_z_m:
            return  # contact forces (a touchdown, a bounce inside the interval) have no bound here
        dv = math.sqrt(sum((d.qvel.item(i) - v0[i]) ** 2 for i in range(3)))
        dt_s = n_steps * self.dt_s
        if dv <= VELOCITY_JUMP_FLOOR_MPS:
            return
        eng = self.lander_cfg.engine
        mass = self.lander_cfg.dry_mass_kg + max(self.propulsion.propellant_kg, 0.0)
        thrust = eng.thrust_max_N * (1.0 + max(eng.thrust_error_frac, 0.0)) * max(self.propulsion.fault_gain, 1.0)
        w_sq = max(w0_sq, d.qvel.item(3) ** 2 + d.qvel.item(4) ** 2 + d.qvel.item(5) ** 2)
        r_com = math.sqrt(sum(c * c for c in self.lander_cfg.com_offset_B_m))
        accel = thrust / mass + abs(float(self.model.opt.gravity[2])) + w_sq * r_com
        bound = VELOCITY_JUMP_FACTOR * accel * dt_s + VELOCITY_JUMP_FLOOR_MPS
        if dv > bound:
            raise PhysicsDivergedError(
                f"physics diverged at t = {self.t_ns / NS_PER_S:.3f} s: with nothing touching the ground the velocity "
                f"changed by {dv:.3g} m/s in {dt_s * 1e3:.3g} ms, more than {bound:.3g} m/s (the engine's strongest "
                f"thrust and gravity, {VELOCITY_JUMP_FACTOR:g} times over): the integration broke down without a "
                f"MuJoCo warning, and nothing after it would be physical"
            )

    def _step_instant(self, n_steps: int, thrust_cmd_N: float, torque: np.ndarray) -> PropulsionOutput:
        """The idealised actuators: the held command's thrust and torque over the interval."""
        out = self.propulsion.apply(thrust_cmd_N, torque, n_steps, self.dt_s)
        self.data.ctrl[self._act_rcs] = out.torque_B_Nm
        self.data.ctrl[self._act_engine] = out.thrust_N
        if out.burn_steps > 0:
            self._apply_fault_torque(True)
            self._advance(out.burn_steps)
        if out.burn_steps < n_steps:
            self._apply_fault_torque(False)
            self.data.ctrl[self._act_engine] = 0.0
            self._advance(n_steps - out.burn_steps)
        self._set_propellant(self.propulsion.propellant_kg)
        # After mj_step, positions, sites, cameras, contacts and sensors still describe the state
        # before the last step; mj_forward makes every truth signal match the time t_ns.
        mujoco.mj_forward(self.model, self.data)
        return out

    def _step_each(self, n_steps: int, thrust_cmd_N: float, torque_cmd_B_Nm: np.ndarray) -> PropulsionOutput:
        """The realistic actuators: thrust, torque and propellant evaluated at every physics step.

        The per-step loop works on floats (the same additions in the same order as on (3,)
        arrays) and reads MuJoCo's warning counters once per step through a live view.
        """
        prop = self.propulsion
        model, data = self.model, self.data
        ctrl, sensordata, qvel, warnings = self._ctrl, self._sensordata, self._qvel, self._warning_number
        i_engine = self._i_engine
        i_rcs_x, i_rcs_y, i_rcs_z = self._i_rcs_xyz
        i_acc_x, i_acc_y, i_acc_z = self._i_acc_xyz
        fault_torque = self._fault_torque_B is not None
        dt_ns = self.physics_dt_ns
        used0 = prop.propellant_kg
        # The command is held over the interval: saturate it once (the per-step path did so every step).
        cmd_x, cmd_y, cmd_z = prop.clamp_torque(torque_cmd_B_Nm).tolist()
        burn_steps = 0
        thrust = 0.0
        impulse_x = impulse_y = impulse_z = 0.0  # sum of the steps' delivered torques [N m]
        f_x, f_y, f_z = self._imu_sum
        w_x, w_y, w_z = self._gyro_sum
        warnings_before = warnings.tolist()
        for _ in range(n_steps):
            thrust, tau_x, tau_y, tau_z, fired = prop.physics_step_xyz(
                thrust_cmd_N, cmd_x, cmd_y, cmd_z, self._step_count, dt_ns)
            burn_steps += fired
            impulse_x += tau_x
            impulse_y += tau_y
            impulse_z += tau_z
            ctrl[i_rcs_x] = tau_x
            ctrl[i_rcs_y] = tau_y
            ctrl[i_rcs_z] = tau_z
            ctrl[i_engine] = thrust
            if fault_torque:
                self._apply_fault_torque(thrust > 0.0)
            mujoco.mj_step(model, data)
            self._step_count += 1
            if warnings.tolist() != warnings_before:  # some counter moved: divergence raises, else go on
                self._check_divergence(warnings_before)
                warnings_before = warnings.tolist()
            # mj_step evaluated the sensors at the step's start with this step's controls: the specific
            # force that acts over the step, summed for the integrating accelerometer (imu_mean_B).
            f_x += sensordata.item(i_acc_x)
            f_y += sensordata.item(i_acc_y)
            f_z += sensordata.item(i_acc_z)
            # The (semi-implicit) integrator turned the attitude with the step's new body rate (the free
            # joint's local angular velocity, the IMU site's axes): summed, the interval's delta-angle.
            w_x += qvel.item(3)
            w_y += qvel.item(4)
            w_z += qvel.item(5)
        self._imu_sum = [f_x, f_y, f_z]
        self._gyro_sum = [w_x, w_y, w_z]
        self._imu_steps += n_steps
        self._set_propellant(prop.propellant_kg)
        mujoco.mj_forward(self.model, self.data)
        # Dry inside the interval, or dry from the start and asked for thrust (a tank loaded empty).
        exhausted = prop.propellant_kg <= 0.0 and (thrust_cmd_N > 0.0 or burn_steps > 0)
        impulse_B = np.array([impulse_x, impulse_y, impulse_z])
        return PropulsionOutput(thrust, impulse_B / max(n_steps, 1), burn_steps, used0 - prop.propellant_kg, exhausted)

    def imu_mean_B(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Mean truth specific force and body rate over the physics steps since the last call, in B, and reset.

        What an integrating IMU reports: its delta-velocity and delta-angle over the sample
        interval, divided by the interval, ((3,) [m/s^2], (3,) [rad/s]). The RCS's pulses,
        through the IMU's lever arm from the centre of mass, then average out instead of being
        point-sampled at a phase locked to their modulation, and the delta-angle is the rotation
        the simulator made (a point-sampled rate leads the attitude by a physics step under
        angular acceleration). None before any realistic step (the instant-actuator path keeps
        point samples).
        """
        if self._imu_steps == 0:
            return None
        out = (np.array(self._imu_sum) / self._imu_steps, np.array(self._gyro_sum) / self._imu_steps)
        self._imu_sum = [0.0, 0.0, 0.0]
        self._gyro_sum = [0.0, 0.0, 0.0]
        self._imu_steps = 0
        return out

    def _advance(self, n: int) -> None:
        before = self._warning_number.tolist()
        mujoco.mj_step(self.model, self.data, nstep=n)
        self._step_count += n
        self._check_divergence(before)

    def _check_divergence(self, before: list[int]) -> None:
        """Raise if a divergence counter grew since ``before`` (MuJoCo's warning counters, a list).

        Raises:
            PhysicsDivergedError: Naming the time now (the end of the step that diverged).
        """
        now = self._warning_number
        for (_, what), w in zip(_DIVERGENCE_WARNINGS, self._i_divergence):
            if int(now[w]) > before[w]:
                raise PhysicsDivergedError(f"physics diverged at t = {self.t_ns / NS_PER_S:.3f} s: MuJoCo reported {what}.")

    # ----------------------------------------------------------------- engine faults (models.faults)
    def set_engine_fault(self, thrust_gain: float, torque_B_Nm: np.ndarray | None,
                         misalignment: tuple[float, float] | None) -> None:
        """Apply the engine faults active now (held until the next call).

        Args:
            thrust_gain: Factor on the delivered thrust (1: none).
            torque_B_Nm: Off-axis torque (3,) [N m] in B while the engine fires; None: none.
            misalignment: (angle_deg, azimuth_deg) of the thrust line from body +z; None: the configured one.
        """
        self.propulsion.fault_gain = float(thrust_gain)
        if torque_B_Nm is None and self._fault_torque_B is not None:
            # The fault has ended: the torque it left on the body ends with it (it was only ever
            # cleared on an engine-off step, so a fault ending mid-burn kept pushing for the rest of the run).
            self.data.xfrc_applied[self._body_lander, 3:6] = 0.0
        self._fault_torque_B = None if torque_B_Nm is None else np.asarray(torque_B_Nm, float)
        if misalignment is None:
            d = self.lander_cfg.engine.thrust_direction_B()
        else:
            a, az = (math.radians(v) for v in misalignment)
            d = np.array([math.sin(a) * math.cos(az), math.sin(a) * math.sin(az), math.cos(a)])
        self.model.actuator_gear[self._act_engine, :3] = d

    def _apply_fault_torque(self, firing: bool) -> None:
        """Hold the thrust-loss fault's torque on the lander (in L) while the engine fires, else none."""
        tau = getattr(self, "_fault_torque_B", None)
        if tau is None:
            return
        if firing:
            R_LB = self.data.xmat[self._body_lander].reshape(3, 3)
            self.data.xfrc_applied[self._body_lander, 3:6] = R_LB @ tau
        else:
            self.data.xfrc_applied[self._body_lander, 3:6] = 0.0

    # ----------------------------------------------------------------- truth signals
    def specific_force_B(self) -> np.ndarray:
        """Truth specific force at the IMU, in B (3,) [m/s^2] (MuJoCo accelerometer)."""
        return self.data.sensordata[self._sens_acc].copy()

    def angular_rate_B(self) -> np.ndarray:
        """Truth angular rate at the IMU, in B (3,) [rad/s]."""
        return self.data.sensordata[self._sens_gyro].copy()

    def altimeter_ray(self) -> tuple[np.ndarray, np.ndarray]:
        """Altimeter origin and unit direction in L, ((3,), (3,))."""
        xmat = self.data.site_xmat[self._site_alt].reshape(3, 3)
        return self.data.site_xpos[self._site_alt].copy(), -xmat[:, 2].copy()

    def altimeter_range_truth(self) -> float:
        """Slant range from the altimeter along its boresight to the terrain [m]; NaN if none."""
        origin, direction = self.altimeter_ray()
        return self.ray_cast(origin, direction)

    def ray_cast(self, origin_L: np.ndarray, direction_L: np.ndarray, groups: tuple[int, ...] | None = None) -> float:
        """Distance along a unit ray to the terrain surface [m]; NaN when it misses.

        Args:
            origin_L: Ray origin in L (3,) [m].
            direction_L: Unit direction in L (3,).
            groups: Geom groups to hit; default the terrain and its patch.
        """
        mask = self._ray_groups
        if groups is not None:
            mask = np.zeros(mujoco.mjNGROUP, np.uint8)
            mask[list(groups)] = 1
        dist = mujoco.mj_ray(self.model, self.data, np.asarray(origin_L, float), np.asarray(direction_L, float),
                             mask, 1, -1, self._ray_geomid)
        return float(dist) if dist >= 0 else math.nan

    def footpad_contacts(self) -> np.ndarray:
        """Which footpads touch the terrain, (4,) bool, order FOOTPAD_NAMES."""
        return self.ground_contacts()[0]

    def ground_contacts(self) -> tuple[np.ndarray, bool]:
        """Which footpads touch the terrain, (4,) bool (order FOOTPAD_NAMES), and whether the hull does."""
        touching = np.zeros(len(self._foot_geoms), bool)
        if self.data.ncon == 0:  # in flight (the contact view below costs more than everything else here)
            return touching, False
        hull = False
        con = self.data.contact
        for i in range(self.data.ncon):
            g1, g2 = con.geom1[i], con.geom2[i]
            other = g2 if g1 == self._geom_terrain else (g1 if g2 == self._geom_terrain else -1)
            touching |= self._foot_geoms == other
            hull |= other == self._geom_hull
        return touching, bool(hull)

    # ----------------------------------------------------------------- camera
    @property
    def altimeter_position_B(self) -> np.ndarray:
        """Altimeter position in the body frame (3,) [m] (mounting calibration)."""
        return self.model.site_pos[self._site_alt].copy()

    @property
    def camera_position_B(self) -> np.ndarray:
        """Camera centre in the body frame (3,) [m] (mounting calibration)."""
        return self.model.cam_pos[self._cam].copy()

    def camera_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Truth camera pose: R_LC (3, 3) (OpenCV camera frame to L) and r_CL_L (3,) [m]."""
        R_L_mj = self.data.cam_xmat[self._cam].reshape(3, 3)
        return R_L_mj @ R_MJCAM_C, self.data.cam_xpos[self._cam].copy()

    def visual_state(self) -> tuple[np.ndarray, ...]:
        """Copies of what a rendered frame is drawn from now: the positions and orientations of the
        bodies, geoms, sites, cameras and lights (``VISUAL_STATE_FIELDS`` of ``mujoco.MjData``)."""
        return tuple(getattr(self.data, name).copy() for name in VISUAL_STATE_FIELDS)

    def set_visual_state(self, state: tuple[np.ndarray, ...]) -> None:
        """Draw the next frames from ``state`` (another world's :meth:`visual_state`, same model).

        Only the fields a frame is drawn from are set (its velocities, forces and contacts are
        left as they were), so this is for a world that renders and never steps."""
        for name, value in zip(VISUAL_STATE_FIELDS, state, strict=True):
            getattr(self.data, name)[...] = value

    def render_signal(self) -> np.ndarray:
        """Noise-free grayscale camera image, (H, W) uint8 [DN].

        Through a render context shared with earlier worlds of this process whose
        textures, heightfields and meshes are the same (``models.render_context``).
        A frame started by :meth:`start_frame` is read when the world has not moved since;
        otherwise the frame is drawn now.
        """
        self.start_frame()
        # The scene is gray (white sun, gray albedo), so one channel carries it all.
        return self._renderer.read_green()

    def start_frame(self) -> None:
        """Start drawing the camera's frame of the world as it is now, to be read by :meth:`render_signal`.

        The GL driver draws it while the caller goes on (``CameraRenderer.start``): the closed loop
        starts a frame it will need before it feeds the other sensors to the flight software. Nothing
        is kept that could go stale: the frame is read only if the world's poses are still those it was
        started with and no other world sharing the render context has drawn since; otherwise
        :meth:`render_signal` draws another.
        """
        if self._renderer is None:
            self._renderer = CameraRenderer(self.model, self.camera_cfg.width_px, self.camera_cfg.height_px,
                                            texture_key=self._texture_key(), culled=self._camera_tiles)
        self._renderer.start(self.data, self._cam)

    def render_depth(self) -> np.ndarray:
        """Z-depth along the boresight, (H, W) float32 [m]."""
        if self._depth_renderer is None:
            cfg = self.camera_cfg
            self._depth_renderer = mujoco.Renderer(self.model, cfg.height_px, cfg.width_px)
            self._depth_renderer.enable_depth_rendering()
        r = self._depth_renderer
        r.update_scene(self.data, camera=self._cam)
        return r.render().astype(np.float32, copy=False)

    def gl_info(self, probe: bool = False) -> dict[str, str] | None:
        """The OpenGL vendor, renderer and version strings of the camera's context.

        Closed-loop results are bit-identical on one machine and one GL build, not across them:
        the summary records these so that a difference can be traced to the renderer.

        Args:
            probe: When nothing has been rendered yet, read them from a small bare context of
                the same backend (no scene, no textures) instead of returning None.
        """
        def strings() -> dict[str, str]:
            get_string = gl_function("glGetString", ctypes.c_char_p, ctypes.c_uint)
            return {name: get_string(code).decode("utf-8", "replace")
                    for name, code in (("vendor", GL_VENDOR), ("renderer", GL_RENDERER), ("version", GL_VERSION))}

        if self._renderer is not None:
            with self._renderer.current():
                return strings()
        if self._depth_renderer is not None:
            self._depth_renderer._gl_context.make_current()
            return strings()
        if not probe:
            return None
        ctx = mujoco.GLContext(64, 64)
        try:
            ctx.make_current()
            return strings()
        finally:
            ctx.free()

    def close(self) -> None:
        """Give the camera's render context back (kept idle for the next world, see
        ``models.render_context``) and free the depth renderer's (also done by garbage collection)."""
        for r in (self._renderer, self._depth_renderer):
            if r is not None:
                r.close()
        self._renderer = self._depth_renderer = None

    def __enter__(self) -> "World":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
