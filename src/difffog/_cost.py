"""Know before you run: the memory and time a forward model will take, from its settings alone.

``estimate_sweep`` / ``estimate_splat`` (the registry's ``estimate`` of each solver; public as
``difffog.estimate(scene, solver, **settings)``) compute the lattice shape the way ``voxelize`` does
(without voxelizing: instant at any size), then adds up the arrays each stage holds at its
peak, and the time per light iteration from measured rates.  ``check_fits(est)`` compares the
peak with the memory available (host RAM on a CPU, device memory on a GPU) and refuses with one
line naming the estimate, what is available and the setting to lower.

Where the numbers come from: every byte count below is the size of an array the code allocates
(named beside it); the per-node overheads that are not one array (the voxelizer's temporaries,
XLA's buffers while a sweep runs) and the process's baseline were measured with
``benchmarks/bench_cost.py`` (peak resident memory of ``difffog render`` in a fresh process,
fog-balls, N = 16-64, M = 2-5, this project's 2-core CPU) and are stated as constants.  The
time rates come from the same benchmark (CPU) and from the GPU issue's H100 measurements of the
current sweep (``_sweep_face_loop``: ~18 µs per loop body there, whatever its size).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

from ._errors import ResourceError

MIB = 1 << 20
GIB = 1 << 30

# ---- constants (measured: benchmarks/bench_cost.py, benchmarks/results/cost.md) -------------
#: resident memory of a process that has imported difffog, jax and trimesh and compiled one
#: small model (fog-balls N = 8, M = 1: the floor every render pays).  Refitted at stop 55,
#: when the light solve became one sweep program instead of six (fog-balls N = 32, M = 2
#: peaked at 704 MiB, 755 with the ± pairs of stop 54 in the same hour, 905 in the table the
#: constants were fitted to before, on another machine); 580 MiB fitted, with the next two
#: constants, to fog-balls N = 32 / 64 / 96 × M = 2 / 3 / 5 and N = 8 × M = 1 / 8 / 12 (every
#: row within 4% of its measured peak; ``benchmarks/results/cost.md``).  Machines differ here
#: by ~100 MB (the splat's floor: 639-690 MiB on the AMD 2-core machine of stop 55, 739 on the
#: Intel one before), which is the estimate's error at small sizes.
BASE_BYTES = 580 * MIB
#: the splat's floor (its process differs from the sweep's) and its bytes per voxel (density,
#: its column integral, the scan's fields, XLA's temporaries): fitted at stop 55 to
#: ``bench_cost.py``'s splat rows, fog-balls N = 32 / 64 / 96 / 128 (639 / 690 / 751 / 840 MiB
#: measured, each within 2%); until then it shared the sweep's floor, 720 MiB, with 16 B/voxel
SPLAT_BASE_BYTES = 630 * MIB
SPLAT_BYTES_PER_VOXEL = 44
#: host bytes per lattice node while voxelizing and preparing (sdf float64 + float32, owner,
#: node type, material, normals, density twice, the shell's maximum filter, the camera
#: geometry's nearest-node indices: ~60 B of named arrays, the rest temporaries)
HOST_BYTES_PER_NODE = 110
#: device bytes per lattice node of the light solve besides the Krylov vectors and the face
#: carries: the problem's per-node fields (σ_t, albedo, sun and sky fluence, six face-frame
#: optical depths, ...: ~160 B named), the face-frame copies a sweep makes (six faces' stacked
#: inputs since stop 55), the light field, the cameras' node fields and XLA's temporaries: 710 B
#: fitted with BASE_BYTES (780 before stop 55)
SOLVE_BYTES_PER_NODE = 710
#: copies of one face's carry (M, D, nu + 2M, nv + 2M) alive at the peak: 2 fitted at stop 55
#: (fog-balls N = 8, M = 8 / 12: 740 / 959 MiB resident, one carry 16 / 96 MiB).  It was 18-19
#: while each of the six face sweeps was its own program with its own buffers (N = 8, M = 16:
#: 7.58 GB resident then, one carry 364 MB; the issue's M = 20: 20.6 GB)
CARRY_COPIES = 2
#: bytes per camera ray (supersample² per pixel, plus edge re-samples) through set-up and march
RAY_BYTES = 400
#: fraction of pixels re-sampled at geometric edges (16 rays each) assumed up front
EDGE_FRACTION = 0.1
EDGE_SAMPLES = 16


def fit_edge_samples(downsample: int) -> int:
    """The edge rays of a fit's camera reduced ``downsample``-fold: a reduced pixel spans k×k
    target pixels, and k times the rays place its edges as finely as the target's own pixels
    (16 at k = 4 left fog-balls' views 1.1-1.2% RMS and +0.2-0.4% in the mean off the box
    average of the full render, and the walls' albedo 0.7% low)."""
    return EDGE_SAMPLES * int(downsample)

#: one light iteration on a CPU = 6·D·n node-and-direction updates at this rate + a per-node
#: cost (sources, face-frame copies, the Krylov step), fitted to bench_cost.py's 9 sweep rows
#: (fog-balls N = 32-96, M = 2-5, this 2-core CPU: each within 0.75-1.2× of the measured)
CPU_UPDATES_PER_S = 0.42e9
#: the same for the isotropic step scheme's native sweep (``forward/sweep/_native.py``): rate and
#: per-node cost fitted (least squares in the relative error) at stop 73, since the surfaces'
#: records come with the plan and the blocks are cut by cost, to bench_cost.py's 9 sweep rows
#: and six renders N = 96 and 128, M = 5 (fog-balls, this 2-core CPU: each within 0.68-1.21×
#: of the measured, where 1.79e9 and 3.4e-7 had grown to 0.65-1.31×, the large lattices' over;
#: benchmarks/results/cost_native_stop73.md; stop 72's, its blocks one 64-byte vector at a
#: time, 1.79e9 and 3.4e-7; stop 65's, the kernel in the world frame, 1.27e9 and 3.6e-7; stop
#: 63's, with the face copies, 1.1e9 and 4.8e-7)
CPU_NATIVE_UPDATES_PER_S = 3.1e9
CPU_NATIVE_SECONDS_PER_NODE = 4.3e-7
#: a CPU's host devices on a mesh of faces (``devices=2``: the ± faces of each axis on two
#: devices, each with the native kernel on its share of the cores, in the face frame: XLA's
#: copies of the sources and fields per face): its Jacobi iteration against one device's,
#: fog-balls N = 64 / 96, M = 3 / 5 and N = 128, M = 5, stop 74 (``bench_sweep.py --devices
#: 1|2``): 1.36, 1.24, 1.69, 1.42 and 1.25-1.6, the median
CPU_MESH_COST = 1.4
#: the share of a face's 16-node row vectors that hold a SURFACE node, for the native sweep's
#: surface records (measured on fog-balls: 0.28-0.34 at N = 128, 0.36-0.49 at N = 64; it falls
#: as 1/N, the surfaces being two-dimensional)
RECORD_SHARE = 0.4
#: the native kernel's general form (the linear scheme, anisotropic moments), seconds per
#: node-and-direction update, plus this per moment, fitted (least squares in the relative error)
#: at stop 65, since the kernel reads and writes the world frame: cloud-plane N = 64, M = 3
#: (linear scheme), this 2-core CPU (bench_sweep.py --phase-order 0 1 2 3): 0.051 / 0.111 /
#: 0.199 / 0.252 s per iteration at K = 0 / 3 / 8 / 15 moments, 0.66 / 1.44 / 2.58 / 3.27 ns
#: per update (stop 64, with the face copies: 0.83 / 1.54 / 2.92 / 4.24); fog-balls M = 3 with
#: the linear scheme 1.38 / 1.23 ns at N = 64 / 128 (0.106 / 0.760 s; its shell of surface
#: nodes costs more than cloud-plane's fog): the estimate 0.65-1.34× the measured over the six rows
CPU_NATIVE_GENERAL_S_PER_UPDATE = 0.9e-9
CPU_NATIVE_S_PER_UPDATE_MOMENT = 0.18e-9
#: an anisotropic phase (``SweepSolver.phase_order`` L, K = (L+1)² − 1 moments): the light
#: iteration's time grows by this fraction per moment (every direction's source built from K
#: moments, K accumulations per update).  cloud-plane N = 64, M = 3, this 2-core CPU
#: (bench_sweep.py --phase-order 0 1 2 3): 0.162 / 0.241 / 0.468 / 0.700 s per iteration at
#: L = 0 / 1 / 2 / 3, i.e. 0.16 / 0.24 / 0.22 per moment
CPU_COST_PER_MOMENT = 0.22
#: the linear-source scheme (``SweepSolver.scheme``; "auto" takes it where a lattice step is
#: optically thick): fog-balls N = 64, M = 3, this 2-core CPU (bench_sweep.py --scheme step /
#: linear, same run): 0.256 against 0.216 s per iteration, XLA temporaries 171 against 144 MiB
#: on a 72³ lattice (its three slope channels)
LINEAR_COST = 0.256 / 0.216
LINEAR_BYTES_PER_NODE = (171 - 144) * 2**20 / 72**3
CPU_SECONDS_PER_NODE = 6.5e-7
#: the sub-stepped scheme (``SweepSolver(scheme="substep")``, opt-in): its light iteration
#: against the step scheme's, per program, and its extra XLA temporaries per lattice node:
#: fog-balls and cloud-tomo N = 64 and 128, M = 3, this 2-core CPU (bench_sweep.py --kernel
#: loop|batched --scheme step|substep; benchmarks/results/bench_substep.md): loop 2.7-3.8×,
#: batched 13.5× (N = 64), temporaries +17 MiB (N = 64) and +184-206 MiB (N = 128)
SUBSTEP_COST_LOOP = 3.3
SUBSTEP_COST_BATCHED = 13.5
SUBSTEP_BYTES_PER_NODE = 100.0
#: the once-scattered sweep (``SweepSolver.once_M`` = K, sub-stepped, XLA's loop, the sun's
#: channel and K moments of order L = 3): seconds per lattice node × direction (6·(2K + 1)²) ×
#: crossing (K − 1).  Measured (cloud-plane, this 2-core CPU, alone, stop 69): 60.6 ns at
#: N = 32, K = 6 (29.9 s); 77.6 ns at N = 24, K = 6 (21.6 s); 62 ns at N = 24, K = 4
#: (3.56 s); scaled for other orders as ``CPU_COST_PER_MOMENT``.  It errs high on larger
#: lattices: 23 ns at N = 64, K = 6 (56 s, where it says 156 s; the fog's slabs and the
#: loop's per-direction overhead do not grow with the vacuum margin's nodes)
ONCE_S_PER_CROSSING = 6.5e-8
#: the sub-stepped scheme's native sweep (``_native.sweep_substep``, stop 70), seconds per
#: lattice node × direction × sub-step (M of them: M − 1 crossings and the node's own), and
#: per angular moment more (each sub-step builds the direction's source from the moments and
#: deposits into them).  Measured on this 2-core CPU, float32, one face sweep at N = 64,
#: M = 3 (``bench_sweep.py --scheme substep``: fog-balls 0.20 s per iteration, 0.87 ns;
#: single faces 0.58-0.82 ns with and without surfaces) and with moments (L = 2, M = 3 and
#: L = 3, M = 6: 0.16-0.17 ns per moment more)
CPU_NATIVE_SUBSTEP_S_PER_UPDATE = 0.87e-9
CPU_NATIVE_SUBSTEP_S_PER_MOMENT = 0.17e-9
#: the once-scattered sweep on the native kernel (its source the sun's channel alone, so the
#: moments cost their deposits only): seconds per lattice node × direction × sub-step at
#: L = 3 (16 channels deposited), cloud-plane, this 2-core CPU (bench_once.py, stop 70):
#: 2.5 ns at N = 24, K = 4 (0.19 s) and N = 32, K = 6 (1.51 s), 2.8 ns at N = 24, K = 6
#: (0.94 s; XLA's loop took 2.7, 18.0 and 34.4 s)
ONCE_NATIVE_S_PER_SUBSTEP = 2.7e-9
#: a reverse-mode gradient's adjoint Krylov solve works on the Jacobi step linearised once
#: (``lx.linearise`` in ``KrylovSolver.init``; a fit's forward-mode tangents, since stop 42,
#: apply it matrix-free and keep none of this), which keeps the sweeps' residuals: XLA
#: temporaries per lattice node and direction (float32, cloud-plane, the light field's
#: Jacobian in 3 unknowns at N = 16-32, M = 2-3; ``benchmarks/fit_memory.py --scaling``,
#: stop 41): ~820-950 B with the step scheme, ~1700 B with the linear one, ~1% more per
#: moment (L = 3: ~1980 B).  Before they were counted the estimate said 0.96 GiB for a fit
#: that peaked at 6.6 GB (N = 24) and 1.9 GiB for one at 20.8 GB (N = 48).  (Since stop 49 a
#: CPU's adjoint products run transposed sweeps, ``SweepSolver.adjoint``, but the parameters'
#: cotangent still linearises one step: the same XLA temporaries, measured by
#: ``benchmarks/bench_adjoint_route.py``.)
LINEARISED_BYTES_STEP = 950
LINEARISED_BYTES_LINEAR = 1700
LINEARISED_PER_MOMENT = 0.011
#: the same with ``SweepSolver.sweep_residuals="recompute"`` (each slab step's inputs kept, the
#: rest recomputed per product; ``fit_memory.py --scaling L:N:M:scheme:recompute``, stop 42):
#: 195 B (0:32:3 step), 384 B (0:24:3 linear), 631 B (3:24:3 linear)
RECOMPUTED_BYTES_STEP = 200
RECOMPUTED_BYTES_LINEAR = 390
RECOMPUTED_PER_MOMENT = 0.043
#: the sub-stepped scheme's linearised sweep (its batched program's residuals: the M − 1
#: crossings' factors per node and direction), kept and recomputed (``fit_memory.py --scaling
#: 0:24:3:substep 0:24:3:substep:recompute``, stop 49: 1616 and 207 B, step 817 B beside it)
LINEARISED_BYTES_SUBSTEP = 1650
RECOMPUTED_BYTES_SUBSTEP = 210
#: a fit's Jacobian: the light field's tangents by forward mode, all unknowns at once, their
#: products matrix-free (``SweepSolver.tangents``): XLA temporaries per number of the solve's
#: state (Λ, its K moments, E) and tangent (float32, cloud-plane, 3 tangents at N = 16-32,
#: M = 3, L = 0 and 3, step and linear: 126-148 floats; ``benchmarks/fit_memory.py
#: --tangents``, stop 42): the Krylov vectors of each tangent's (flexible) GMRES and the
#: batched sweeps' temporaries
TANGENT_BYTES_PER_STATE = 600
#: a gradient differentiates the cameras in reverse mode (the march's hand-written VJP): its
#: residuals, per ray and march step (2·max(lattice shape) steps): cloud-plane, both cameras
#: / 4 (12454 rays) at N = 16 / 24 / 32: 714 / 961 / 1222 MiB of XLA temporaries, ~1240-1290 B
#: per ray and step (stop 42, ``benchmarks/fit_memory.py --cameras``, the transpose of the
#: VJP that a fit's columns were until stop 60)
CAMERA_VJP_BYTES_PER_RAY_STEP = 1300
#: a fit's Jacobian takes the cameras' columns by forward mode (``_march.forward_mode``, since
#: stop 60), which keeps nothing per step: its XLA temporaries per ray, march step and
#: unknown: cloud-plane at N = 24, 3 unknowns, 12454 rays, 64 steps: 54 MiB (against 2156 MiB
#: for the transpose of the VJP in the same run; ``benchmarks/fit_memory.py``)
CAMERA_JVP_BYTES_PER_RAY_STEP = 25


def linearised_sweep_bytes(nodes: int, M: int, linear: bool, K: int, residuals: str,
                           substep: bool = False) -> int:
    """What one linearised Jacobi step keeps (a gradient's adjoint works on it): per lattice
    node and direction, by scheme, moments and ``SweepSolver.sweep_residuals`` ("keep" or
    "recompute"; resolved)."""
    step, lin, per_moment = ((RECOMPUTED_BYTES_STEP, RECOMPUTED_BYTES_LINEAR,
                              RECOMPUTED_PER_MOMENT) if residuals == "recompute" else
                             (LINEARISED_BYTES_STEP, LINEARISED_BYTES_LINEAR,
                              LINEARISED_PER_MOMENT))
    if substep:
        step = (RECOMPUTED_BYTES_SUBSTEP if residuals == "recompute"
                else LINEARISED_BYTES_SUBSTEP)
    D = (2 * int(M) + 1) ** 2
    return int(nodes * D * (lin if linear else step) * (1.0 + per_moment * K))


#: one loop body of the sweep (a tile of 16 rows × one direction) on a GPU: the loop path is
#: bound by launch latency, not by bandwidth (H100: 18 µs per body, the GPU issue's figures)
GPU_SECONDS_PER_BODY = 18e-6
#: the batched sweep (kernel="batched", the GPU's default) on a GPU: node-and-direction updates
#: per second (H100, fog-balls N = 128, M = 5: 0.0213 s per iteration, the GPU issue's figures)
GPU_BATCHED_UPDATES_PER_S = 72e9
#: the batched sweep on a CPU is this many times slower than the loop (fog-balls N = 48, M = 3,
#: this 2-core CPU: 0.50 against 0.058 s per iteration)
CPU_BATCHED_SLOWDOWN = 8.7
#: host set-up: seconds per node (voxelize, prepare), per node × direction × M (the segment
#: masks: 2|L| samples per direction, 64 nodes per word), per sampled offset of the six faces'
#: directions (6·D·2M NumPy calls: what dominates at large M) and per camera ray (exact hits,
#: the sun's depth: 0.34 s for fog-balls' 199,270 rays); fitted by relative least squares to
#: fog-balls' set-up (forward_model's stages) at N/M = 32/2, 32/5, 64/3, 64/5, 96/5, 128/3,
#: 128/5 and 8/16 on this 2-core CPU: each within 0.89–1.14× of the measured
SETUP_S_PER_NODE = 8.9e-7
SETUP_S_PER_NODE_DIRECTION_STEP = 3.1e-10
SETUP_S_PER_SEGMENT_SAMPLE = 6.6e-6
SETUP_S_PER_RAY = 1.7e-6
#: the sun's visibility from exact shadow rays (open domains with shapes and a sun): a ray per
#: node and 8-27 more per cell near a shadow's edge, added after the constants above were
#: fitted.  Since stop 48 (rays along the one sun direction, spheres and boxes on the
#: lattice's axes) 0.14-0.20 µs per node for fog-balls, 0.41-0.50 ring-box, 0.65-0.96
#: translucent-cube, 0.97-1.37 cloud-plane at N = 128 / 64 (this 2-core CPU; 2.1-3.6 µs
#: before); on two cores it runs beside the faces' masks
SETUP_S_PER_NODE_SHADOW = 0.5e-6
#: the sub-stepped scheme's per-node weight scale (``_kernel.substep_weight_scale``, NumPy on
#: the host, since stop 50): seconds per node × direction × crossing (M − 1 per segment) and per
#: NumPy call (six faces × slabs × D × (M − 1)).  Measured (``bench_sweep.py --scheme
#: substep``, prepare s, this 2-core CPU): +0.5 s at 64³, +1.6-2.0 s at 128³ (M = 3,
#: fog-balls and cloud-tomo); these give 0.52 and 2.5 s
SETUP_S_PER_SUBSTEP_CROSSING = 1e-8
#: the native blocked sweep's surface records (``_native.surface_records``, six faces, since
#: stop 73), seconds per node: fog-balls N = 96, M = 5, prepare 0.96-1.04 s with them against
#: 0.67-0.84 s without (alternated in one process, this 2-core CPU)
SETUP_S_PER_NODE_RECORDS = 2e-7
SETUP_S_PER_SUBSTEP_CALL = 2e-5
#: the splat's set-up: a fixed part (its footprint and kernel programs) and a part per voxel
#: (bench_cost.py: 3.1 / 3.9 / 4.9 s at N = 32 / 64 / 96)
SPLAT_SETUP_S = 2.6
SPLAT_SETUP_S_PER_NODE = 2.5e-6
#: compiling the light solve and the cameras, the first time in a process (10-15 s measured
#: for fog-balls at N = 8-64; a later solve with the same shapes reuses it)
COMPILE_S = 15.0
#: GMRES steps a light solve typically takes (fog-balls 11, thick fog with the preconditioner
#: 20; 6 in thin fog): the solve time is quoted for this many
TYPICAL_ITERATIONS = 20


@dataclass(frozen=True)
class CostEstimate:
    """What a forward model will cost, before it is built.

    shape: the lattice (nx, ny, nz) with its vacuum margin; directions: per cube face.
    memory: bytes per component at the solve's peak; peak_bytes: their sum.
    seconds_per_iteration: one bounce (six sweeps) of the light solve; setup_s: host set-up;
    once_s: the sweep of the sun's once-scattered light on its finer direction set, once per
    solve (``SweepSolver.once_M``; 0 without).
    """

    solver: str
    shape: tuple[int, int, int]
    M: int
    rays: int
    memory: dict = field(default_factory=dict)
    seconds_per_iteration: float = 0.0
    setup_s: float = 0.0
    backend: str = "cpu"
    once_s: float = 0.0

    @property
    def nodes(self) -> int:
        return math.prod(self.shape)

    @property
    def peak_bytes(self) -> int:
        return int(sum(self.memory.values()))

    @property
    def solve_s(self) -> float:
        return TYPICAL_ITERATIONS * self.seconds_per_iteration + self.once_s

    def as_dict(self) -> dict:
        return {"solver": self.solver, "lattice_shape": list(self.shape), "M": self.M,
                "nodes": self.nodes, "camera_rays": self.rays, "backend": self.backend,
                "peak_bytes": self.peak_bytes,
                "memory_bytes": {k: int(v) for k, v in self.memory.items()},
                "seconds_per_iteration": self.seconds_per_iteration,
                "solve_s_typical": self.solve_s, "typical_iterations": TYPICAL_ITERATIONS,
                "setup_s": self.setup_s, "once_s": self.once_s}

    def setup_text(self) -> str:
        return _secs(self.setup_s)

    def lines(self) -> list[str]:
        parts = ", ".join(f"{k} {_size(v)}" for k, v in self.memory.items() if v >= MIB)
        out = [f"memory     ~{_size(self.peak_bytes)} at the peak ({parts})"]
        if self.seconds_per_iteration > 0:  # an iterated light solve (the sweep)
            out.append(f"time       ~{_secs(self.seconds_per_iteration)} per light iteration on "
                       f"{self.backend}, ~{_secs(self.solve_s)} for a typical solve of "
                       f"{TYPICAL_ITERATIONS}; set-up ~{_secs(self.setup_s)}, compiling "
                       f"~{_secs(COMPILE_S)} the first time")
        else:
            out.append(f"time       set-up ~{_secs(self.setup_s)}")
        return out


def _size(b: float) -> str:
    if b >= GIB:
        return f"{b / GIB:.1f} GiB"
    return f"{b / MIB:.0f} MiB"


def _secs(s: float) -> str:
    if s >= 3600:
        return f"{s / 3600:.1f} h"
    if s >= 60:
        return f"{s / 60:.1f} min"
    return f"{s:.2g} s"


def lattice_shape(scene, resolution: int, margin: int) -> tuple[int, int, int]:
    """The lattice ``voxelize(scene, resolution, M, margin=margin)`` would build."""
    from .geometry._lattice import _Grid

    return tuple(int(x) for x in _Grid.from_domain(scene.domain, int(resolution), int(margin)).shape)


def _cameras(scene, cameras):
    """The scene's cameras a model renders (``cameras``: names, or None for all)."""
    return [c for c in scene.cameras if cameras is None or c.name in cameras]


def camera_rays(scene, cameras, supersample: int, edge_samples: int = EDGE_SAMPLES) -> int:
    """Rays the cameras cast: supersample² per pixel (+ the sweep's edge re-samples, 0 for
    none)."""
    px = sum(c.width * c.height for c in _cameras(scene, cameras))
    extra = EDGE_FRACTION * int(edge_samples)
    return int(px * (supersample ** 2 + extra))


def estimate_splat(scene, *, resolution: int = 64, supersample: int = 1, cameras=None,
                   sheets: int | None = None, backend: str | None = None,
                   **_ignored) -> CostEstimate:
    """The :class:`CostEstimate` of the splat (the registry's ``estimate`` for it)."""
    f = 4  # float32
    shape = lattice_shape(scene, resolution, 0)
    n = math.prod(shape)
    rays = camera_rays(scene, cameras, int(supersample), edge_samples=0)
    ext = max(shape)
    K = int(sheets) if sheets else int(math.ceil(math.sqrt(3) * ext)) + 2
    texels = int((math.sqrt(2) * ext + 8) ** 2)
    mem = {"process": SPLAT_BASE_BYTES,
           "volume": n * SPLAT_BYTES_PER_VOXEL,
           # light_D (K + W + 1, hs, ws) per camera
           "shadow buffers": len(_cameras(scene, cameras)) * (K + 7) * texels * f,
           # eye footprints: eye_D, eye_up (K, P) (eye_uv is built per sheet)
           "eye footprints": K * rays * 2 * f}
    return CostEstimate("splat", shape, 0, rays, mem, 0.0,
                        setup_s=SPLAT_SETUP_S + SPLAT_SETUP_S_PER_NODE * n,
                        backend=backend or _backend())


def estimate_sweep(scene, *, resolution: int = 64, M: int = 3, supersample: int = 2,
                   cameras=None, restart: int = 30, backend: str | None = None,
                   kernel: str = "auto", gradient: bool = False, tangent_solves: int = 0,
                   phase_order="auto", scheme: str = "auto", tangents: str = "matrix-free",
                   sweep_residuals: str = "auto", edge_samples: int = EDGE_SAMPLES,
                   once_M: int | None = None, devices: int = 1, mesh=None,
                   **_ignored) -> CostEstimate:
    """The :class:`CostEstimate` of the sweep (the registry's ``estimate`` for it).

    kernel: the sweep's program ("auto": the backend's, as ``SweepSolver`` chooses it);
    gradient: add a reverse-mode gradient's adjoint solve: its Krylov vectors and the linearised
        sweeps it works on (``jax.grad``; the density fit);
    tangent_solves: add that many tangent solves (forward mode: a fit's Jacobian has one per
        unknown), each with its Krylov vectors (and the linearised sweeps, with
        ``tangents="linearised"``);
    phase_order: the anisotropic phase's order ("auto": the scene's, as ``SweepSolver``);
    scheme: the transport scheme ("auto": the solver's rule, judged from the scene);
    tangents, sweep_residuals, once_M: as ``SweepSolver``'s (once_M: one more sub-stepped
        sweep per solve on that direction set, ``ONCE_S_PER_CROSSING``; the lattice's shell
        follows it);
    devices, mesh: as ``SweepSolver``'s.  On a CPU the host devices share the cores: a mesh
        of faces alone runs the native kernel per face in the face frame (``CPU_MESH_COST``
        times one device's iteration, no surface records), one that splits the plane runs
        XLA's loop; and each host device holds its own copy of the light's fields and GMRES's
        vectors in the one machine's memory (fog-balls, 2 host devices against one, stop 74:
        +449 MB at N = 64, M = 3, +953 MB at N = 96, M = 3, +3.1 GB at N = 128, M = 5, where
        those two parts are 0.37, 1.1 and 2.7 GB).  On a GPU (each device its own memory, which
        the estimate is compared with) a mesh changes nothing here: not measured."""
    backend = backend or _backend()
    if mesh is None:
        from .forward.sweep._solver import mesh_shape_for

        mesh = mesh_shape_for(int(devices or 1))
    ndev = math.prod(mesh)
    if kernel == "auto":
        from .forward.sweep._kernel import kernel_for

        kernel = kernel_for(backend)
    f = 4  # float32
    M = int(M)
    from .forward.sweep._solver import SweepSolver

    once = SweepSolver(M=M, phase_order=phase_order, once_M=once_M).resolved_once_M(scene)
    from .geometry._lattice import VACUUM_MARGIN

    shape = lattice_shape(scene, resolution, VACUUM_MARGIN)
    n = math.prod(shape)
    D = (2 * M + 1) ** 2
    rays = camera_rays(scene, cameras, int(supersample), int(edge_samples))
    surfaces = bool(scene.shapes)
    K = (SweepSolver(phase_order=phase_order).resolved_phase_order(scene) + 1) ** 2 - 1
    state = n * (2 + K if surfaces else 1 + K)  # Λ and its K moments, E
    nu = sorted(shape)[-1] + 2 * M
    nv = sorted(shape)[-2] + 2 * M
    mem = {
        "process": BASE_BYTES,
        "lattice (host)": n * HOST_BYTES_PER_NODE,
        # FaceGeometry.blocked: (nw, nu, nv, ceil(D/8)) uint8 per face on the host and the
        # device, and while they are built a mask and its face-frame copy per worker thread
        "blocking masks": ((12 + 2 * min(6, os.cpu_count() or 1)) * n * math.ceil(D / 8)
                           if surfaces else 0),
        # per-node fields; an anisotropic phase adds its moments' sources and accumulators
        # (face-frame copies of 1 + K + 1 channels in and 1 + K out): ~4 (K + 1) floats
        "light solve": n * (SOLVE_BYTES_PER_NODE + 16 * K * f),
        # GMRES: restart + 1 Krylov vectors (+ restart preconditioned ones, flexible GMRES,
        # where the diffusion preconditioner is chosen), x, b, and the light's state (its
        # fixed point as it leaves the solve, LightField.state, since stop 60)
        "Krylov vectors": ((2 * restart if _diffusive(scene) else restart) + 4) * state * f,
        # the sweep's carry (M, D, nu + 2M, nv + 2M): CARRY_COPIES of it (measured)
        "face carries": CARRY_COPIES * M * D * nu * nv * f,
        "cameras": rays * RAY_BYTES,
    }
    resolved = _scheme(scene, resolution, M, phase_order, scheme)
    linear, substep = resolved == "linear", resolved == "substep"
    if gradient:
        mem["cameras' VJP"] = int(CAMERA_VJP_BYTES_PER_RAY_STEP * rays * 2 * max(shape))
    if tangent_solves:
        mem["cameras' columns"] = int(CAMERA_JVP_BYTES_PER_RAY_STEP * rays * 2 * max(shape)
                                      * int(tangent_solves))
    if tangent_solves:
        # each tangent's GMRES and its share of the vmapped sweeps: TANGENT_BYTES_PER_STATE per
        # number of the solve's state (nothing per direction: the products are matrix-free)
        mem["tangent solves"] = int(tangent_solves) * TANGENT_BYTES_PER_STATE * state
        # where they start and what they reach (a fit's next step starts from its last
        # accepted point's tangents, since stop 61): the guesses in the step's data, the new
        # tangents and their copy in the optimizer's state, which holds the light state too
        mem["tangents' starts"] = (3 * int(tangent_solves) + 1) * state * f
    if gradient:
        mem["adjoint"] = 41 * state * f  # lineax GMRES, restart 40
    if gradient or (tangent_solves and tangents == "linearised"):
        from .forward.sweep._solver import sweep_residuals_for

        residuals = sweep_residuals_for(sweep_residuals, n, M, linear, K, substep)
        mem["linearised sweeps"] = linearised_sweep_bytes(n, M, linear, K, residuals, substep)
    if backend == "gpu" and kernel == "batched":
        per_iter = 6 * D * n / GPU_BATCHED_UPDATES_PER_S
    elif backend == "gpu":
        slabs = -(-max(shape) // M)
        bodies = 6 * slabs * max(1, -(-nu // 16)) * D
        per_iter = bodies * GPU_SECONDS_PER_BODY
    general = False  # the native kernel's general form: its own figure (no factors below)
    native = False  # the native sweep (XLA's loop without it)
    if backend != "gpu" and kernel == "loop":
        from .forward.sweep import _native

        native = _native.expected() and mesh[1] == mesh[2] == 1  # (no halos: one device's plane)
    if backend != "gpu":
        rate, per_node = CPU_UPDATES_PER_S, CPU_SECONDS_PER_NODE
        general = native and (K > 0 or linear or substep)
        if native and substep:
            per_iter = 6 * D * n * M * (CPU_NATIVE_SUBSTEP_S_PER_UPDATE
                                        + CPU_NATIVE_SUBSTEP_S_PER_MOMENT * K)
        elif general:
            per_iter = 6 * D * n * (CPU_NATIVE_GENERAL_S_PER_UPDATE
                                    + CPU_NATIVE_S_PER_UPDATE_MOMENT * K)
        else:
            if native:
                rate, per_node = CPU_NATIVE_UPDATES_PER_S, CPU_NATIVE_SECONDS_PER_NODE
            per_iter = 6 * D * n / rate + per_node * n
        if kernel == "batched":
            per_iter *= CPU_BATCHED_SLOWDOWN
        if native and ndev > 1:
            per_iter *= CPU_MESH_COST
    if not general:  # (the GPU's programs are assumed to grow alike: not measured there)
        per_iter *= 1.0 + CPU_COST_PER_MOMENT * K
        if linear:
            per_iter *= LINEAR_COST
    if linear:
        mem["light solve"] += n * LINEAR_BYTES_PER_NODE
    if substep:  # (measured on a CPU; the GPU's batched program assumed to grow alike)
        if not general:  # (the native kernel's figure above is its own)
            per_iter *= SUBSTEP_COST_LOOP if kernel == "loop" else SUBSTEP_COST_BATCHED
        mem["light solve"] += int(n * SUBSTEP_BYTES_PER_NODE)
    from .forward.sweep import _native

    if (surfaces and native and ndev == 1 and not (K or linear or substep)
            and _native.records_apply(D, shape)):
        # the native blocked sweep's surface records, made with the plan (``_native.
        # surface_records``): per face an index of the rows' 16-node vectors, and for those
        # with a SURFACE node (fog-balls: 28-34% of them at N = 128, 36-49% at N = 64; taken
        # as RECORD_SHARE) 16 lanes of a normal and the blocking words, the lanes' OR, a flag
        lanes, words = _native.RECORD_LANES, -(-D // 32)
        per_record = lanes * (12 + 4 * words) + math.ceil(D / 8) + 1
        mem["surface records"] = int(6 * n / lanes * (4 + RECORD_SHARE * per_record))
        records_s = SETUP_S_PER_NODE_RECORDS * n
    else:
        records_s = 0.0
    if ndev > 1 and backend == "cpu":
        mem["other devices' copies"] = (ndev - 1) * (mem["light solve"] + mem["Krylov vectors"])
    from .geometry._hits import shadows_exactly
    setup = (SETUP_S_PER_NODE * n + SETUP_S_PER_RAY * rays
             + ((SETUP_S_PER_NODE_DIRECTION_STEP * n * D * M
                 + SETUP_S_PER_SEGMENT_SAMPLE * 6 * D * 2 * M) if surfaces else 0)
             + (SETUP_S_PER_NODE_SHADOW * n if shadows_exactly(scene) else 0) + records_s)
    if substep:
        setup += (M - 1) * D * (SETUP_S_PER_SUBSTEP_CROSSING * n
                                + SETUP_S_PER_SUBSTEP_CALL * 6 * -(-max(shape) // M))
    once_s = 0.0
    if once:  # its sweep (always sub-stepped): time, its geometry's set-up, carries, residuals
        sub = estimate_sweep(scene, resolution=resolution, M=once, supersample=supersample,
                             cameras=cameras, restart=restart, backend=backend, kernel=kernel,
                             gradient=gradient, phase_order=phase_order,
                             scheme="substep", tangents=tangents,
                             sweep_residuals=sweep_residuals, edge_samples=edge_samples)
        if native:
            once_s = ONCE_NATIVE_S_PER_SUBSTEP * n * 6 * (2 * once + 1) ** 2 * once
        else:
            once_s = ONCE_S_PER_CROSSING * n * 6 * (2 * once + 1) ** 2 * (once - 1)
        once_s *= (1.0 + CPU_COST_PER_MOMENT * K) / (1.0 + CPU_COST_PER_MOMENT * 15)
        # its faces (not the cameras again, nor the sun's shadow rays: it has the solve's beam)
        setup += sub.setup_s - SETUP_S_PER_RAY * rays - (
            SETUP_S_PER_NODE_SHADOW * sub.nodes if shadows_exactly(scene) else 0)
        # (its carries while it runs, beyond the solve's, which come after)
        mem["once-scattered sweep"] = max(0, sub.memory["face carries"] - mem["face carries"])
        if "linearised sweeps" in sub.memory:
            mem["once-scattered sweep"] += sub.memory["linearised sweeps"]
    return CostEstimate("sweep", shape, M, rays, mem, per_iter, setup, backend, once_s)


def _density_max(fog) -> float:
    if getattr(fog, "density", None) is None:
        return 1.0
    import numpy as np

    return float(np.max(fog.density))


def _linear(scene, resolution: int, M: int, phase_order, scheme: str) -> bool:
    """Whether the sweep will run the linear-source scheme (``SweepSolver.resolved_scheme``,
    judged from the scene's density grid and domain instead of the lattice)."""
    return _scheme(scene, resolution, M, phase_order, scheme) == "linear"


def _scheme(scene, resolution: int, M: int, phase_order, scheme: str) -> str:
    """The transport scheme the sweep will run (``SweepSolver.resolved_scheme``, judged from
    the scene's density grid and domain instead of the lattice)."""
    from types import SimpleNamespace

    from .forward.sweep._solver import SweepSolver

    extent = max(b - a for a, b in zip(scene.domain.min, scene.domain.max))
    fog = scene.fog
    lat = SimpleNamespace(peak_density=_density_max(fog) if fog is not None else 0.0,
                          h=extent / int(resolution))
    solver = SweepSolver(M=int(M), phase_order=phase_order, scheme=scheme)
    return solver.resolved_scheme(scene, lat)


def _diffusive(scene) -> bool:
    """Whether precondition="auto" will choose the diffusion preconditioner (the solver's rule,
    judged from the scene's density grid and domain instead of the lattice)."""
    from .forward.sweep._solver import DIFFUSION_OPTICAL_SIZE, diffusive_size

    fog = scene.fog
    if fog is None:
        return False
    dmax = _density_max(fog)
    extent = max(b - a for a, b in zip(scene.domain.min, scene.domain.max))
    return diffusive_size(fog, dmax, extent) >= DIFFUSION_OPTICAL_SIZE


def _backend() -> str:
    try:
        import jax

        return jax.default_backend()
    except Exception:  # pragma: no cover - jax is a dependency
        return "cpu"


def machine() -> dict:
    """What JAX runs on here: backend, its devices (count and kind) and the JAX version — for
    ``difffog info`` and ``report.json``."""
    import jax

    devs = jax.devices()
    return {"backend": jax.default_backend(), "devices": len(devs),
            "device_kind": ", ".join(sorted({d.device_kind for d in devs})),
            "jax": jax.__version__}


def machine_line(info: dict | None = None) -> str:
    """:func:`machine` in one line, e.g. ``cpu, 1 device (cpu), JAX 0.10.2``."""
    m = info or machine()
    n = m["devices"]
    return f"{m['backend']}, {n} device{'s' if n != 1 else ''} ({m['device_kind']}), JAX {m['jax']}"


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else what ``platform`` says)."""
    import platform

    try:
        with open("/proc/cpuinfo") as f:
            return next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def load_average() -> str:
    """The 1 / 5 / 15-minute load average as text ("n/a" where the OS has none)."""
    try:
        return " / ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def copy_bandwidth(nbytes: int = 256 * 2**20, repeat: int = 5, threads: int = 1) -> float:
    """The machine's copy bandwidth in GB/s (bytes read + bytes written per second, median of
    ``repeat``): NumPy ``copyto`` of a float32 array of ``nbytes`` into a preallocated one,
    split over ``threads`` threads (``copyto`` releases the GIL).  The roofline that speed
    figures are stated against, measured in the same run as they are."""
    import concurrent.futures as cf
    import statistics
    import time

    import numpy as np

    n = nbytes // 4
    src = np.random.default_rng(0).random(n, dtype=np.float32)
    dst = np.empty_like(src)
    parts = [slice(i * n // threads, (i + 1) * n // threads) for i in range(threads)]
    with cf.ThreadPoolExecutor(threads) as pool:
        def copy():
            list(pool.map(lambda s: np.copyto(dst[s], src[s]), parts))

        copy()  # page in
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            copy()
            times.append(time.perf_counter() - t)
    return 2 * nbytes / statistics.median(times) / 1e9


def available_bytes(backend: str | None = None) -> tuple[int, str]:
    """(bytes, what) the run can use: the GPU's memory, else the host's available RAM."""
    backend = backend or _backend()
    if backend == "gpu":
        try:
            import jax

            stats = jax.devices()[0].memory_stats() or {}
            if "bytes_limit" in stats:
                return int(stats["bytes_limit"]), "GPU memory"
        except Exception:  # pragma: no cover
            pass
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "available RAM"
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free RAM"
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 1 << 62, "memory (unknown)"


def check_fits(est: CostEstimate, *, force: bool = False, what: str = "this run") -> str | None:
    """Refuse (DifffogError, one line) when ``est`` will not fit; a warning text above half of
    the available memory (None otherwise).  ``force`` turns the refusal into the warning."""
    avail, kind = available_bytes(est.backend)
    need = est.peak_bytes
    lower = _what_to_lower(est)
    msg = (f"{what} needs ~{_size(need)} at its peak (estimate: lattice "
           f"{'x'.join(map(str, est.shape))}" + (f", M = {est.M}" if est.M else "")
           + f"), {kind} is {_size(avail)}")
    if need > avail and not force:
        raise ResourceError(f"{msg}; {lower}, or pass --force / force=True to try anyway")
    if need > avail / 2:
        return f"{msg}; {lower} if it swaps"
    return None


def _what_to_lower(est: CostEstimate) -> str:
    m = est.memory
    big = max((k for k in m if k != "process"), key=lambda k: m[k])
    if big == "face carries" and est.M > 2:
        return f"lower M (-M/--directions; the face carries, {_size(m[big])}, grow as M³·N²)"
    if big == "cameras":
        return "lower the camera resolution or --supersample"
    return f"lower the resolution (-N; the {big}, {_size(m[big])}, grow as N³)"
