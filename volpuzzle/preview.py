"""preview.png: the assembled puzzle and an exploded view side by side, shaded, one colour per piece.

Rendered headless with matplotlib's Agg backend; each piece is simplified first so that painting stays fast.
"""

import numpy as np


def _simplified(mesh, faces=1500):
    if len(mesh.faces) <= faces:
        return mesh.vertices, mesh.faces
    try:
        import fast_simplification

        v, f = fast_simplification.simplify(mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32),
                                            target_reduction=1.0 - faces / len(mesh.faces))
        if len(f):
            return np.asarray(v, float), np.asarray(f)
    except Exception:  # noqa: BLE001 - a preview falls back to the full mesh rather than failing the build
        pass
    return mesh.vertices, mesh.faces


def _triangles(parts, offsets):
    tris, cols = [], []
    light = np.array([0.35, -0.5, 0.8])
    light /= np.linalg.norm(light)
    for (mesh, rgb), off in zip(parts, offsets):
        v, f = _simplified(mesh)
        t = v[f] + off
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
        c = np.clip(np.asarray(rgb, float)[None, :] / 255.0 * shade[:, None], 0, 1)
        tris.append(t)
        cols.append(c)
    return np.concatenate(tris), np.concatenate(cols)


def render_preview(path, meshes, colors, size=(1600, 800), explode=0.6, title=None):
    """Write a PNG: left the assembled puzzle, right exploded. meshes: list of Trimesh in mm; colors (n, 3) uint8."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    centers = np.array([m.centroid for m in meshes])
    center = centers.mean(axis=0)
    exploded = (centers - center) * explode
    fig = plt.figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    for k, (offs, label) in enumerate(((np.zeros_like(centers), "assembled"), (exploded, "exploded"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        tris, cols = _triangles(list(zip(meshes, colors)), offs)
        coll = Poly3DCollection(tris, facecolors=cols, edgecolors="none", linewidths=0, antialiased=False)
        ax.add_collection3d(coll)
        lo, hi = tris.reshape(-1, 3).min(axis=0), tris.reshape(-1, 3).max(axis=0)
        span = np.maximum(hi - lo, 1e-3 * (hi - lo).max())
        ax.set_xlim(lo[0], lo[0] + span[0])
        ax.set_ylim(lo[1], lo[1] + span[1])
        ax.set_zlim(lo[2], lo[2] + span[2])
        # Equal scale on every axis, framed on the model rather than on a cube around it.
        ax.set_box_aspect(tuple(span), zoom=1.25)
        ax.view_init(elev=28, azim=-60)
        ax.set_axis_off()
        ax.set_title(label, fontsize=14)
    if title:
        fig.suptitle(title, fontsize=16)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0)
    fig.savefig(path, dpi=100)
    plt.close(fig)
