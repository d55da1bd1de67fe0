"""Writes the binary fixtures of the bad scenes (run from this folder; the outputs are committed)."""

import numpy as np

g = np.ones((4, 4, 4), np.float32)
np.savez("density-wrong-key.npz", cloud=g)
np.savez("density-2d.npz", density=np.ones((4, 4), np.float32))
np.savez("density-int.npz", density=np.ones((4, 4, 4), np.int32))
nan = g.copy()
nan[1, 2, 3] = np.nan
np.savez("density-nan.npz", density=nan)
neg = g.copy()
neg[0, 0, 1] = -0.5
np.savez("density-negative.npz", density=neg)
np.save("density.npy", g)
with open("not-an-archive.npz", "w") as f:
    f.write("this is not a zip archive\n")
with open("garbage.obj", "w") as f:
    f.write("hello\nthis is not a mesh\n")
with open("mesh.foo", "w") as f:
    f.write("v 0 0 0\n")
tetra = "v 0 0 0\nv 0.2 0 0\nv 0 0.2 0\nv 0 0 0.2\n"
with open("open-tetra.obj", "w") as f:  # one face missing: 3 boundary edges
    f.write(tetra + "f 1 3 2\nf 1 2 4\nf 1 4 3\n")
with open("closed-tetra.obj", "w") as f:
    f.write(tetra + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
