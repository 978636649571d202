"""Editing a live robosuite scene through its MjModel: cameras, table textures, object colours, sizes.

robosuite's TextureModder does not work on mujoco 3, so everything here writes the MjModel arrays
directly (``cam_pos``/``cam_quat``, ``geom_rgba``/``geom_matid``, ``mat_rgba``, ``tex_data``) and
re-uploads changed textures through the offscreen render context. Object sizes cannot change in a
compiled model, so :func:`scale_bodies_xml` rescales them in the MJCF before compilation.

The noise injectors use the same helpers at run time: move a camera with
``set_camera_pose(model, camera_id(model, "agentview"), pos, quat)`` and swap the table texture
with ``set_material_texture(model, ctx, material_id(model, "table_ceramic"), image)``.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

VISUAL_GROUP = 1  # robosuite renders geom group 1 (visual meshes); group 0 holds collision geoms


def _id(model: mujoco.MjModel, kind: mujoco.mjtObj, name: str, what: str) -> int:
    i = mujoco.mj_name2id(model, kind, name)
    if i < 0:
        count = {"camera": model.ncam, "material": model.nmat, "body": model.nbody}[what]
        names = [mujoco.mj_id2name(model, kind, j) for j in range(count)]
        raise ValueError(f"no {what} named {name!r} in the model; valid {what}s: {', '.join(n for n in names if n)}")
    return i


def camera_id(model: mujoco.MjModel, name: str) -> int:
    return _id(model, mujoco.mjtObj.mjOBJ_CAMERA, name, "camera")


def material_id(model: mujoco.MjModel, name: str) -> int:
    return _id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name, "material")


def body_id(model: mujoco.MjModel, name: str) -> int:
    return _id(model, mujoco.mjtObj.mjOBJ_BODY, name, "body")


# ---- cameras ---------------------------------------------------------------------------------

def camera_pose(model: mujoco.MjModel, data: mujoco.MjData, cam: int) -> dict:
    """World pose of a camera after the last forward pass: {"pos": [x,y,z], "quat": [w,x,y,z]}."""
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, data.cam_xmat[cam])
    return {"pos": data.cam_xpos[cam].round(6).tolist(), "quat": quat.round(6).tolist()}


def set_camera_pose(model: mujoco.MjModel, cam: int, pos, quat) -> None:
    """Place a camera (pose relative to its parent body, the world for robosuite's agentview)."""
    model.cam_pos[cam] = np.asarray(pos, dtype=float)
    model.cam_quat[cam] = np.asarray(quat, dtype=float) / np.linalg.norm(quat)


def offset_quat(quat, rot_deg) -> np.ndarray:
    """Rotate a camera quaternion [w,x,y,z] by (roll, pitch, yaw) degrees about its own x, y, z axes."""
    delta = np.zeros(4)
    mujoco.mju_euler2Quat(delta, np.deg2rad(np.asarray(rot_deg, dtype=float)), "XYZ")
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(quat, dtype=float), delta)
    return out


def look_at_quat(pos, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Quaternion [w,x,y,z] of a MuJoCo camera at `pos` looking at `target` (cameras look along -z)."""
    back = np.asarray(pos, dtype=float) - np.asarray(target, dtype=float)
    z = back / np.linalg.norm(back)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.stack([x, y, z], axis=1).ravel())
    return quat


# ---- textures and colours --------------------------------------------------------------------

def texture_dir() -> Path:
    import robosuite

    return Path(robosuite.__file__).parent / "models" / "assets" / "textures"


def texture_names() -> list[str]:
    """Names of the texture images shipped with robosuite (`wood-tiles`, `white-bricks`, ...)."""
    return sorted(p.stem for p in texture_dir().glob("*.png"))


@functools.lru_cache(maxsize=32)
def load_texture(name: str, width: int, height: int) -> np.ndarray:
    """A robosuite texture image resized to (height, width, 3) uint8."""
    from PIL import Image

    path = texture_dir() / f"{name}.png"
    if not path.exists():
        raise ValueError(f"unknown texture {name!r} (no {path}); valid textures: {', '.join(texture_names())}")
    img = Image.open(path).convert("RGB").resize((width, height), Image.BILINEAR)
    return np.asarray(img, dtype=np.uint8)


def material_texture(model: mujoco.MjModel, mat: int) -> int:
    """The RGB texture id of a material (-1 when it has none)."""
    return int(model.mat_texid[mat, mujoco.mjtTextureRole.mjTEXROLE_RGB])


def texture_view(model: mujoco.MjModel, tex: int) -> np.ndarray:
    """A writable (height, width, channels) view of a texture's pixels inside ``model.tex_data``."""
    w, h, c = model.tex_width[tex], model.tex_height[tex], model.tex_nchannel[tex]
    adr = model.tex_adr[tex]
    return model.tex_data[adr: adr + w * h * c].reshape(h, w, c)


def set_material_texture(model: mujoco.MjModel, render_ctx, mat: int, image: np.ndarray | str) -> None:
    """Overwrite the pixels of a material's texture (an image or a robosuite texture name) and
    upload them to the renderer. The image is resized to the texture's size."""
    tex = material_texture(model, mat)
    if tex < 0:
        raise ValueError(f"material {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_MATERIAL, mat)!r} has no texture")
    view = texture_view(model, tex)
    h, w = view.shape[:2]
    if isinstance(image, str):
        image = load_texture(image, int(w), int(h))
    elif image.shape[:2] != (h, w):
        from PIL import Image

        image = np.asarray(Image.fromarray(np.asarray(image, dtype=np.uint8)).resize((int(w), int(h))))
    view[...] = image[..., : view.shape[2]]
    if render_ctx is not None:
        render_ctx.upload_texture(tex)


def body_geoms(model: mujoco.MjModel, body: int, visual_only: bool = True) -> np.ndarray:
    """Geoms of a body and its descendants (visual ones only by default)."""
    bodies = [b for b in range(model.nbody) if _descends(model, b, body)]
    geoms = np.flatnonzero(np.isin(model.geom_bodyid, bodies))
    if visual_only:
        geoms = geoms[model.geom_group[geoms] == VISUAL_GROUP]
    return geoms


def _descends(model: mujoco.MjModel, b: int, ancestor: int) -> bool:
    while b > 0 and b != ancestor:
        b = model.body_parentid[b]
    return b == ancestor


def set_geom_color(model: mujoco.MjModel, geoms, rgba) -> None:
    """Flat colour for geoms: drop their material (its texture would tint the colour) and set rgba."""
    geoms = np.asarray(geoms, dtype=int)
    model.geom_matid[geoms] = -1
    model.geom_rgba[geoms] = np.asarray(rgba, dtype=np.float32)


# ---- sizes (before compilation) --------------------------------------------------------------

def scale_bodies_xml(xml: str, bodies, scale: float) -> str:
    """Scale bodies (geometry, sites, child bodies, meshes, inertia) in an MJCF string by `scale`."""
    if scale == 1.0 or not bodies:
        return xml
    root = ET.fromstring(xml)
    meshes = {m.get("name"): m for m in root.iter("mesh")}
    found = set()
    for body in root.iter("body"):
        if body.get("name") in bodies:
            found.add(body.get("name"))
            _scale_children(body, scale, meshes, scaled_meshes=set())
    missing = set(bodies) - found
    if missing:
        raise ValueError(f"cannot scale bodies {sorted(missing)}: not in the model")
    return ET.tostring(root, encoding="unicode")


def _mul(el: ET.Element, attr: str, factor: float) -> None:
    if el.get(attr) is not None:
        el.set(attr, " ".join(repr(float(v) * factor) for v in el.get(attr).split()))


def _scale_children(el: ET.Element, s: float, meshes: dict, scaled_meshes: set) -> None:
    for child in el:
        _mul(child, "pos", s)
        if child.tag in ("geom", "site"):
            mesh = child.get("mesh")
            if mesh and mesh not in scaled_meshes:
                scaled_meshes.add(mesh)
                m = meshes[mesh]
                m.set("scale", m.get("scale", "1 1 1"))
                _mul(m, "scale", s)
            elif not mesh:
                _mul(child, "size", s)
            _mul(child, "fromto", s)
        elif child.tag == "inertial":
            _mul(child, "mass", s**3)
            _mul(child, "diaginertia", s**5)
        elif child.tag == "body":
            _scale_children(child, s, meshes, scaled_meshes)
