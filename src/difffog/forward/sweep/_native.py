"""The face sweep as a native CPU kernel (an XLA FFI custom call).

``_kernel._sweep_face_loop`` expresses the CPU sweep in XLA loops (slabs → row tiles →
directions); XLA runs each direction's body as separate kernels, ~1.5 ns per node and
direction on this 2-core CPU whatever the tile (issue 20: 12% of the copy roofline).
``native/sweep_face.cc`` does the same arithmetic with the planes visited one residue chain at
a time (a ray from plane sM + m arrives at (s + 1)M + m) and one vectorised pass per direction
and row tile.  It serves the values of the step scheme (the default for fog whose lattice steps
are optically thin: since stop 71, on a face of at least 2¹⁸ node-and-direction updates (2²¹
and two threads or more until stop 72), by blocks of directions, each block swept alone
through the whole face with its node data read once per block, the blocks shared among the
CPU's cores) and of the linear scheme (thick steps), isotropic or with a Henyey–Greenstein fog's angular moments
and the sun's phase channel (the general form: each direction's source built from the node's
channels, Λ's moments summed), on a CPU; the rest with one chain's carry kept in the last-level
cache, the tiles of each plane shared among the cores.
Since stop 70 it also serves the sub-stepped scheme (``sweep_substep``: the planes in sweep
order, each plane's crossing factors built once while it lies within reach of the next
arrivals, the directions shared among the cores, each depositing into its own window of
Λ, folded afterwards), and that scheme's transpose (``sweep_substep_transposed``: a
gradient's adjoint light solve, the planes in reverse).  A device mesh's halo, another backend
and the other derivatives (the sweeps' JVPs, the step and linear schemes' transposes) stay JAX
programs.

``native/gram_schmidt.cc``, in the same library, orthogonalizes each GMRES step against the
live rows of its Krylov basis only (``gram_schmidt``; XLA's products read every row), and
``native/sky_pass.cc`` computes the sky's first collision of an open domain (``sky_pass``:
every light solve's fixed pass, with the moments and the linear scheme's slope where asked;
3-5x faster than XLA's program since stop 74; its derivatives stay XLA's).

The library is compiled on first use with the machine's C++ compiler (``$CXX``, else
``c++``), five objects at once (the sweep's ``PARTS``, the Gram–Schmidt's, the sky's), against
jaxlib's FFI headers, into ``$XDG_CACHE_HOME/difffog/native`` (``~/.cache``), named by a hash
of the sources, the flags, the compiler, jaxlib and the CPU (``-march=native``): a later
process loads it (milliseconds).  Without a compiler, or if the build fails, the sweep keeps
XLA's loop, GMRES XLA's products and the sky pass XLA's program (same values; :func:`status`
says why).  ``DIFFFOG_NATIVE=0`` turns them all off.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import hashlib
import math
import os
import shlex
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np

from ..._cache import user_cache_root

#: the environment variable that turns the native kernel off ("0", "off", "no", "false")
NATIVE_ENV = "DIFFFOG_NATIVE"
#: the custom call's name: this prefix and the source's hash, so that a compiled program kept by
#: JAX's persistent cache never calls a kernel built from another source
TARGET = "difffog_sweep_face"
_SOURCE = Path(__file__).with_name("native") / "sweep_face.cc"
#: GMRES's Gram–Schmidt over the live rows of its basis (``gram_schmidt``), in the same library
_GS_SOURCE = _SOURCE.with_name("gram_schmidt.cc")
GS_TARGET = "difffog_gram_schmidt"
#: the sky's first collision (``sky_pass``), in the same library
_SKY_SOURCE = _SOURCE.with_name("sky_pass.cc")
SKY_TARGET = "difffog_sky_pass"
#: the header both the sweep's and the sky's sources include (vector exp, the threads' barrier)
_HEADER = _SOURCE.with_name("native_common.h")
#: the sub-stepped scheme's sweep (``sweep_substep``), in the sweep's source
SUBSTEP_TARGET = "difffog_sweep_substep"
#: and its transpose (``sweep_substep_transposed``: a gradient's adjoint)
SUBSTEP_T_TARGET = "difffog_sweep_substep_t"
_FLAGS = ["-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-fopenmp-simd",
          "-fno-math-errno", "-fno-trapping-math", "-pthread"]
#: the sweep's source is compiled as this many objects (``DIFFFOG_PART``: the FFI handler,
#: float, double), at once with the Gram–Schmidt's, then linked: the three 9.3 s on this
#: project's 2-core CPU against 15.4–18.2 s as one; with the Gram–Schmidt's 9.5–11.8 s, and
#: since stop 70 (the sub-stepped kernels in the float and double objects) 13.3 s
PARTS = 3
#: builds not loaded for this many days are deleted when another is built (one per source,
#: compiler, jaxlib or CPU change, ~100 KB each; a machine that still uses one rebuilds it)
PRUNE_DAYS = 30
#: the per-node data of a row tile, bytes (about half of one core's L2 on this project's CPU)
TILE_BYTES = 448 * 1024
_LOCK = threading.Lock()
_STATE: dict = {}


def _cpu_tag() -> str:
    """The CPU's model and instruction-set flags (the build is ``-march=native``: a home folder
    shared by machines whose CPUs differ must not share it)."""
    import platform

    seen = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key = line.split(":", 1)[0].strip()
                if key in ("model name", "flags", "Features", "CPU part") and key not in seen:
                    seen[key] = line.strip()
    except OSError:
        pass
    return "\n".join(seen[k] for k in sorted(seen)) + platform.processor() + platform.machine()


def _compiler() -> str | None:
    """``$CXX`` (if it runs), else ``c++`` or ``g++`` on the PATH; None if none."""
    cxx = os.environ.get("CXX")
    if cxx:
        return shutil.which(cxx.split()[0]) and cxx
    return shutil.which("c++") or shutil.which("g++")


def _turned_off() -> bool:
    return os.environ.get(NATIVE_ENV, "").strip().lower() in ("0", "off", "no", "false")


def expected() -> bool:
    """Whether the CPU sweep will be native, without building it (the cost model
    asks before anything is built): as :func:`available` once it has been asked, else turned
    on and a compiler at hand."""
    with _LOCK:
        if "ok" in _STATE:
            return _STATE["ok"]
    return not _turned_off() and bool(_compiler())


def _build() -> Path:
    """The compiled library's path (compiling it first if needed); raises OSError or
    subprocess.CalledProcessError where it cannot be built."""
    import jax
    import jaxlib

    cxx = _compiler()
    if not cxx:
        raise OSError("no C++ compiler (c++ or $CXX) on PATH")
    cxx = shlex.split(cxx)  # $CXX may carry a wrapper or flags ("ccache g++")
    version = subprocess.run([*cxx, "--version"], capture_output=True, text=True,
                             timeout=30).stdout.splitlines()[:1]
    src = b"\0".join(p.read_bytes() for p in (_SOURCE, _GS_SOURCE, _SKY_SOURCE, _HEADER))
    libs = ["-lmvec"] if ctypes.util.find_library("mvec") else []  # glibc's vector math
    key = hashlib.sha256(b"\0".join([src, " ".join(_FLAGS + libs + [f"parts={PARTS}"]).encode(),
                                     str(version).encode(),
                                     jaxlib.__version__.encode(), _cpu_tag().encode()]))
    folder = user_cache_root() / "native"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        folder = Path(tempfile.gettempdir()) / f"difffog-native-{os.getuid()}"
        folder.mkdir(parents=True, exist_ok=True)
    lib = folder / f"sweep_face-{key.hexdigest()[:16]}.so"
    if lib.exists():
        try:
            os.utime(lib)  # in use: kept by the pruning below
        except OSError:
            pass
        return lib
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=folder)
    os.close(fd)
    try:  # built under a temporary name, then renamed: nothing half-written is ever loaded
        with tempfile.TemporaryDirectory(dir=folder) as objs:
            _compile_parts(cxx, [f"-I{jax.ffi.include_dir()}"], Path(objs), tmp, libs)
        os.replace(tmp, lib)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    _prune(folder, keep=lib)
    return lib


def _compile_parts(cxx: list[str], include: list[str], objs: Path, out: str,
                   libs: list[str]) -> None:
    """Compile the sweep's ``PARTS`` objects (the handler, float, double) and the Gram–Schmidt's
    at once and link them into ``out``; raises subprocess.CalledProcessError (its stderr the
    compiler's) or subprocess.TimeoutExpired."""
    flags = [f for f in _FLAGS if f != "-shared"]
    units = [(_SOURCE, [f"-DDIFFFOG_PART={k}"]) for k in range(PARTS)] + [(_GS_SOURCE, []),
                                                                           (_SKY_SOURCE, [])]
    procs, outs, objects = [], [], []
    try:
        for k, (source, defines) in enumerate(units):
            objects.append(str(objs / f"part{k}.o"))
            cmd = [*cxx, *flags, *include, *defines, "-c", str(source), "-o", objects[-1]]
            procs.append((cmd, subprocess.Popen(cmd, stdout=subprocess.PIPE,
                                                stderr=subprocess.PIPE, text=True)))
        outs = [proc.communicate(timeout=300) for _, proc in procs]
    finally:
        for _, proc in procs:  # on a timeout: the others stopped, every pipe closed
            if proc.poll() is None:
                proc.kill()
            proc.communicate()
    for (cmd, proc), (stdout, stderr) in zip(procs, outs):
        if proc.returncode:
            raise subprocess.CalledProcessError(proc.returncode, cmd, stdout, stderr)
    subprocess.run([*cxx, "-shared", "-pthread", *objects, "-o", out, *libs], check=True,
                   capture_output=True, text=True, timeout=300)


def _prune(folder: Path, keep: Path, days: float = PRUNE_DAYS) -> list[Path]:
    """Delete the kernel's builds in ``folder`` (other than ``keep``) not loaded for ``days``
    (their modification time, which a load refreshes); returns what was deleted."""
    import time

    old = time.time() - days * 86400.0
    gone = []
    for p in folder.glob("sweep_face-*.so"):
        try:
            if p != keep and p.stat().st_mtime < old:
                p.unlink()
                gone.append(p)
        except OSError:  # another process's, or already gone
            pass
    return gone


def available() -> bool:
    """True if the native kernel is built (on first call) and registered with XLA for the CPU;
    False where it is turned off or cannot be built (:func:`status` says why)."""
    with _LOCK:
        if "ok" in _STATE:
            return _STATE["ok"]
        if _turned_off():
            _STATE.update(ok=False, why=f"turned off ({NATIVE_ENV})")
            return False
        try:
            import jax

            lib = _build()
            handle = ctypes.cdll.LoadLibrary(str(lib))
            names = {}  # each custom call named by its source's hash (see TARGET)
            for key, prefix, source, symbol in (
                    ("target", TARGET, _SOURCE, "DifffogSweepFace"),
                    ("gs_target", GS_TARGET, _GS_SOURCE, "DifffogGramSchmidt"),
                    ("substep_target", SUBSTEP_TARGET, _SOURCE, "DifffogSweepSubstep"),
                    ("substep_t_target", SUBSTEP_T_TARGET, _SOURCE, "DifffogSweepSubstepT"),
                    ("sky_target", SKY_TARGET, _SKY_SOURCE, "DifffogSkyPass")):
                names[key] = f"{prefix}_{hashlib.sha256(source.read_bytes()).hexdigest()[:12]}"
                jax.ffi.register_ffi_target(names[key],
                                            jax.ffi.pycapsule(getattr(handle, symbol)),
                                            platform="cpu")
            _STATE.update(ok=True, why=str(lib), handle=handle, **names)
        except (OSError, subprocess.SubprocessError, AttributeError) as e:
            lines = (getattr(e, "stderr", "") or str(e)).strip().splitlines() or [type(e).__name__]
            first = next((ln for ln in lines if "error" in ln.lower()), lines[-1])
            _STATE.update(ok=False, why=f"not built ({first.strip()})")
        return _STATE["ok"]


def serves(dtype) -> bool:
    """Whether the native kernels serve arrays of ``dtype`` here: JAX's default backend a CPU,
    float32 or float64, the library built (:func:`available`)."""
    import jax

    return (jax.default_backend() == "cpu" and np.dtype(dtype) in (np.float32, np.float64)
            and available())


def status() -> str:
    """One line: where the native kernel was loaded from, or why it is not used."""
    ok = available()
    return ("native (" + _STATE["why"] + ")") if ok else ("XLA loop: " + _STATE["why"])


def _threads() -> int:
    """Threads per kernel call: ``DIFFFOG_THREADS`` where set (e.g. 1 for each of several
    processes sharing the cores: each thread's share of a sweep is fixed, so that its sums
    come out the same to the bit, and a thread whose core is taken holds up the call), else
    the cores per host device."""
    import jax

    env = os.environ.get("DIFFFOG_THREADS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ValueError(f"DIFFFOG_THREADS={env!r}: expected a whole number of threads "
                             "(e.g. DIFFFOG_THREADS=1), or unset it") from None
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    return max(1, cores // max(1, jax.local_device_count("cpu")))


#: the lanes of the kernel's float32 vectors (64 bytes): the width of the surfaces' records
RECORD_LANES = 16
#: the blocked sweep's threshold: a face of at least this many node-and-direction updates
#: (``sweep_face.cc``: BLOCKED_MIN_UPDATES), the isotropic step scheme
BLOCKED_MIN_UPDATES = 1 << 18


def records_apply(D: int, face_shape: tuple[int, int, int]) -> bool:
    """Whether the blocked sweep serves a face of ``face_shape`` (nw, nu, nv) with D directions
    (the isotropic step scheme's, float32): where the plan makes the surfaces' records."""
    return D * math.prod(face_shape) >= BLOCKED_MIN_UPDATES


def surface_records(normal: np.ndarray, blocked: np.ndarray, surf: np.ndarray,
                    D: int) -> dict[str, np.ndarray]:
    """The blocked sweep's records of a face's surfaces (``sweep_face.cc``: ``SurfVecs``), made
    once with the plan instead of at every call (fog-balls, N = 128, M = 5: 17-20 ms a face on
    each of two threads, 15% of an iteration).  Each row of the face is cut into vectors of
    ``RECORD_LANES`` nodes (nv // 16 + 1 of them, the last partial or empty); a vector with a
    normal, a SURFACE node or a blocked segment has a record: whether it touches a surface
    (a normal or a SURFACE node), its blocking bytes' OR over the lanes, its normals (3, 16)
    and its blocking bits (16 lanes of ceil(D / 32) little-endian 32-bit words, bit d % 32 of
    word d // 32: direction d).

    normal (nw, nu, nv, 3) float32, blocked (nw, nu, nv, ceil(D / 8)) uint8, surf (nw, nu, nv)
    bool, all in the face frame → index (nw, nu, nv // 16 + 1) int32 (the record's number or
    -1), touch (R,) uint8, any (R, nb) uint8, normal (R, 3, 16) float32, bits (R, NW, 16)
    uint32."""
    lanes = RECORD_LANES
    nw, nu, nv, nb = blocked.shape
    nch = nv // lanes + 1
    pad = [(0, 0), (0, 0), (0, nch * lanes - nv)]
    nrm = np.pad(np.asarray(normal, np.float32), pad + [(0, 0)]).reshape(nw, nu, nch, lanes, 3)
    bits = np.pad(np.asarray(blocked, np.uint8), pad + [(0, 0)]).reshape(nw, nu, nch, lanes, nb)
    touch = (np.pad(np.asarray(surf, bool), pad).reshape(nw, nu, nch, lanes).any(-1)
             | (nrm != 0).any((-2, -1)))
    any_ = np.bitwise_or.reduce(bits, axis=3)  # (nw, nu, nch, nb)
    keep = touch | any_.any(-1)
    index = np.where(keep, np.cumsum(keep).reshape(keep.shape) - 1, -1).astype(np.int32)
    words = -(-D // 32)
    b = bits[keep]  # (R, 16, nb)
    b = np.pad(b, [(0, 0), (0, 0), (0, 4 * words - nb)]).view("<u4")  # (R, 16, NW)
    return dict(index=index, touch=touch[keep].astype(np.uint8), any=any_[keep],
                normal=np.ascontiguousarray(nrm[keep].transpose(0, 2, 1)),
                bits=np.ascontiguousarray(b.transpose(0, 2, 1)).astype(np.uint32))


def sweep_face(Q, B, tau, normal, bits, free, surf, bc, length_k, kidx, weight, unit, start, *,
               M: int, ns: int, segment: tuple[int, int, bool, bool], surfaces: bool,
               periodic: tuple[bool, bool, bool], table=None, nk: int = 0, slope=None,
               frame: tuple[int, int] | None = None, records=None, exits: bool = True):
    """The custom call: ``_sweep_face_loop``'s arrays in the face frame (nw, nu, nv[, ...]),
    unslabbed (the kernel visits the ns·M planes of its slabs itself: padding after an open
    sweep axis, a periodic one's warm-up in wrap order), and its direction constants → Λ, E
    (nw, nu, nv) and the radiance leaving the last M planes (M, D, nu, nv).  ``segment`` =
    (s0, s1, attenuate, fluence): the slabs [s0, s1) do the fog step and the fluence as told,
    the others neither.

    The general form: Q (nw, nu, nv, 1 + J [+ 3]) with ``table`` (D, J), its first ``nk``
    columns the moments' (Λ then (nw, nu, nv, 1 + nk) when nk > 0), and with ``slope`` (D, 3)
    the linear scheme (Q's last three channels the slope h∇Q).

    frame: (axis, sign) of the face: Q and B are then in the world frame (nx, ny, nz[, C]) and so
    are Λ and E, which the kernel reads and writes at each face node's world node (the face's
    copies, ``_kernel.to_face``, and the transposes back are not made); the geometry and τ stay
    in the face frame.

    records: the surfaces' records made with the plan (``surface_records``: a mapping with its
    five arrays), which the blocked sweep reads instead of making them; used for float32 only
    (the layout's), else ignored.  exits: False skips the radiance leaving (returned as None;
    at N = 128, M = 5 it is 40 MB a face that a light solve never reads)."""
    import jax
    import jax.numpy as jnp

    dt = Q.dtype
    nw, nu, nv = tau.shape[:3]
    C = 1 if Q.ndim == 3 else int(Q.shape[3])
    if frame is None:
        world, (wb, sw, su, sv), out_shape = 0, (0, 0, 0, 0), (nw, nu, nv)
    else:
        world, out_shape = 1, tuple(Q.shape[:3])
        wb, sw, su, sv = world_strides(out_shape, *frame)
    J = 0 if table is None else int(table.shape[1])
    linear = slope is not None
    D = (2 * M + 1) ** 2
    K = int(length_k.shape[0])
    nb = int(bits.shape[-1]) if surfaces else 1
    item = np.dtype(dt).itemsize
    # rows per tile: tall, so that each direction's rows stream from memory as one block, with
    # the tile's per-node data in L2 (K factors and 2K sums, Q, B, τ, Λ, E, a normal, bytes:
    # 3K + 12 values; the general form: C channels, 4K factors, 1 + nk sums, 8 more); the
    # isotropic step scheme's blocks of directions on a large face choose their own
    # (``sweep_face.cc``: BLOCK_TILE_BYTES, in L1)
    per_node = (3 * K + 12) if C == 1 and not linear else (C + 4 * K + 1 + nk + 8)
    tile = int(max(1, min(nu, TILE_BYTES // (per_node * nv * item))))
    lam_shape = out_shape + ((1 + nk,) if nk else ())
    out = [jax.ShapeDtypeStruct(lam_shape, dt), jax.ShapeDtypeStruct(out_shape, dt)] + [
        jax.ShapeDtypeStruct((M, D, nu, nv) if exits else (1,), dt),
        jax.ShapeDtypeStruct((2, D, nu + 2 * M, nv + 2 * M), dt)]
    s0, s1, att, fl = segment
    per_w, per_u, per_v = periodic
    call = jax.ffi.ffi_call(_STATE["target"], out, vmap_method="sequential")
    f = lambda x: jnp.asarray(x, dt)  # noqa: E731  (the kernel reads every float as Q's type)
    i64 = np.int64
    use = records is not None and surfaces and dt == np.float32
    rec = ((jnp.asarray(records["index"], jnp.int32), jnp.asarray(records["touch"], jnp.uint8),
            jnp.asarray(records["any"], jnp.uint8), jnp.asarray(records["normal"], jnp.float32),
            jnp.asarray(records["bits"], jnp.uint32)) if use else
           tuple(jnp.zeros((1,), t) for t in (jnp.int32, jnp.uint8, jnp.uint8, jnp.float32,
                                              jnp.uint32)))
    lam, irr, exit_, _ = call(
        Q, f(B), f(tau), f(normal), jnp.asarray(bits, jnp.uint8), jnp.asarray(free, jnp.bool_),
        jnp.asarray(surf, jnp.bool_), f(bc), f(length_k), jnp.asarray(kidx, jnp.int32),
        f(weight), f(unit), jnp.asarray(start, jnp.int32),
        f(jnp.zeros((1,)) if table is None else table), f(jnp.zeros((1,)) if slope is None else slope),
        *rec,
        M=i64(M), nw=i64(nw), nu=i64(nu), nv=i64(nv), ns=i64(ns), D=i64(D), K=i64(K),
        nb=i64(nb), s0=i64(s0), s1=i64(s1), threads=i64(_threads()), tile=i64(tile),
        surfaces=i64(surfaces), per_w=i64(per_w), per_u=i64(per_u), per_v=i64(per_v),
        att_in=i64(att), fl_in=i64(fl), C=i64(C), J=i64(J), NK=i64(nk), linear=i64(linear),
        world=i64(world), wb=i64(wb), sw=i64(sw), su=i64(su), sv=i64(sv), records=i64(use))
    return lam, irr, exit_ if exits else None


def sweep_substep(Q, B, tau, normal, bits, free, surf, bc, length_k, kidx, weight, unit, start,
                  sub_start, *, M: int, ns: int, segment: tuple[int, int, bool, bool],
                  surfaces: bool, periodic: tuple[bool, bool, bool], table=None, nk: int = 0):
    """The sub-stepped scheme's custom call (``substep_sweep`` in ``native/sweep_face.cc``):
    ``_kernel._sweep_face_substep_loop``'s arrays in the face frame (nw, nu, nv[, C]) and its
    direction constants, ``start`` (D, 2) the arrivals' and ``sub_start`` (M − 1, D, 2) the
    crossings' window origins → Λ over the sub-steps whose light is known (nw, nu, nv[, 1 +
    nk]), E (nw, nu, nv) and the radiance leaving the last M planes (M, D, nu, nv).
    ``segment`` = (s0, s1, fog, fluence): the slabs [s0, s1) take the sub-stepped fog step
    (``_kernel._substep_fog_slabs``), the others only move the rays."""
    import jax
    import jax.numpy as jnp

    dt = Q.dtype
    nw, nu, nv = tau.shape[:3]
    C = 1 if Q.ndim == 3 else int(Q.shape[3])
    J = 0 if table is None else int(table.shape[1])
    D = (2 * M + 1) ** 2
    nb = int(bits.shape[-1]) if surfaces else 1
    lam_shape = (nw, nu, nv) + ((1 + nk,) if nk else ())
    out = [jax.ShapeDtypeStruct(lam_shape, dt), jax.ShapeDtypeStruct((nw, nu, nv), dt),
           jax.ShapeDtypeStruct((M, D, nu, nv), dt)]
    s0, s1, fog, fl = segment
    per_w, per_u, per_v = periodic
    call = jax.ffi.ffi_call(_STATE["substep_target"], out, vmap_method="sequential")
    f = lambda x: jnp.asarray(x, dt)  # noqa: E731  (the kernel reads every float as Q's type)
    i64 = np.int64
    return tuple(call(
        Q, f(B), f(tau), f(normal), jnp.asarray(bits, jnp.uint8), jnp.asarray(free, jnp.bool_),
        jnp.asarray(surf, jnp.bool_), f(bc), f(length_k), jnp.asarray(kidx, jnp.int32),
        f(weight), f(unit), jnp.asarray(start, jnp.int32), jnp.asarray(sub_start, jnp.int32),
        f(jnp.zeros((1,)) if table is None else table),
        M=i64(M), nw=i64(nw), nu=i64(nu), nv=i64(nv), ns=i64(ns), D=i64(D),
        K=i64(length_k.shape[0]), nb=i64(nb), s0=i64(s0), s1=i64(s1), threads=i64(_threads()),
        surfaces=i64(surfaces), per_w=i64(per_w), per_u=i64(per_u), per_v=i64(per_v),
        att_in=i64(fog), fl_in=i64(fl), C=i64(C), J=i64(J), NK=i64(nk)))


def sweep_substep_transposed(lam_bar, irr_bar, tau, normal, bits, free, surf, length_k, kidx,
                             weight, unit, start, sub_start, *, M: int, ns: int,
                             segment: tuple[int, int, bool], surfaces: bool,
                             periodic: tuple[bool, bool, bool], table=None, nk: int = 0):
    """The transpose of ``sweep_substep``'s linear map (Q, B) → (Λ, E) at fixed τ and zero
    boundary radiance (``substep_transposed`` in ``native/sweep_face.cc``,
    ``_kernel._sweep_face_substep_transposed``'s values): Λ̄ (nw, nu, nv[, 1 + nk]), already
    scaled by the geometry's weight scale, and Ē → Q̄ (nw, nu, nv[, 1 + J]) and B̄.
    ``segment`` = (s0, s1, fog): the slabs [s0, s1) took the fog step."""
    import jax
    import jax.numpy as jnp

    dt = lam_bar.dtype
    nw, nu, nv = tau.shape[:3]
    J = 0 if table is None else int(table.shape[1])
    D = (2 * M + 1) ** 2
    nb = int(bits.shape[-1]) if surfaces else 1
    out = [jax.ShapeDtypeStruct((nw, nu, nv) + ((1 + J,) if J else ()), dt),
           jax.ShapeDtypeStruct((nw, nu, nv), dt)]
    s0, s1, fog = segment
    per_w, per_u, per_v = periodic
    call = jax.ffi.ffi_call(_STATE["substep_t_target"], out, vmap_method="sequential")
    f = lambda x: jnp.asarray(x, dt)  # noqa: E731
    i64 = np.int64
    return tuple(call(
        lam_bar, f(irr_bar), f(tau), f(normal), jnp.asarray(bits, jnp.uint8),
        jnp.asarray(free, jnp.bool_), jnp.asarray(surf, jnp.bool_), f(length_k),
        jnp.asarray(kidx, jnp.int32), f(weight), f(unit), jnp.asarray(start, jnp.int32),
        jnp.asarray(sub_start, jnp.int32), f(jnp.zeros((1,)) if table is None else table),
        M=i64(M), nw=i64(nw), nu=i64(nu), nv=i64(nv), ns=i64(ns), D=i64(D),
        K=i64(length_k.shape[0]), nb=i64(nb), s0=i64(s0), s1=i64(s1), threads=i64(_threads()),
        surfaces=i64(surfaces), per_w=i64(per_w), per_u=i64(per_u), per_v=i64(per_v),
        att_in=i64(fog), J=i64(J), NK=i64(nk)))


def gram_schmidt(V, a, live):
    """One Arnoldi step's classical Gram–Schmidt applied twice against the rows [0, ``live``)
    of V (rows, n) (``live`` traced): (h (rows,), zero beyond ``live``; w = a − hᵀV; ‖w‖), as
    ``_krylov``'s XLA products compute them, reading only the live rows
    (``native/gram_schmidt.cc``).  Call where :func:`available`."""
    import jax
    import jax.numpy as jnp

    dt = V.dtype
    call = jax.ffi.ffi_call(_STATE["gs_target"], (
        jax.ShapeDtypeStruct(a.shape, dt), jax.ShapeDtypeStruct(V.shape[:1], dt),
        jax.ShapeDtypeStruct((), dt)), vmap_method="sequential")
    w, h, norm = call(V, jnp.asarray(a, dt), jnp.asarray(live, jnp.int32),
                      threads=np.int64(_threads()))
    return h, w, norm


def sky_pass(sigma, opaque, normal, table, chan=None, nh: int = 0, slope: bool = False):
    """The sky's first collision (``native/sky_pass.cc``): (fluence, irradiance, channels),
    each (nx, ny, nz) and (nx, ny, nz, nh + 3·slope) (a 1-element dummy without any), from
    sigma and opaque (nx, ny, nz) and normal (nx, ny, nz, 3) in the world frame, table (K, 12),
    one row per sky direction grouped by the axis its sheets run along, and chan (K, nh +
    3·slope) the channels' weights (``_uncollided._sky_table``), with
    ``_uncollided._sheet_sweep``'s arithmetic.  Call where :func:`available`."""
    import jax
    import jax.numpy as jnp

    dt = sigma.dtype
    out = jax.ShapeDtypeStruct(sigma.shape, dt)
    C = int(nh) + (3 if slope else 0)
    mom = jax.ShapeDtypeStruct(sigma.shape + (C,) if C else (1,), dt)
    call = jax.ffi.ffi_call(_STATE["sky_target"], (out, out, mom), vmap_method="sequential")
    return call(sigma, jnp.asarray(opaque, jnp.uint8), jnp.asarray(normal, dt),
                jnp.asarray(table, dt), jnp.zeros((1,), dt) if chan is None else
                jnp.asarray(chan, dt), threads=np.int64(_threads()), nh=np.int64(nh),
                slope=np.int64(bool(slope)))


@functools.lru_cache(maxsize=64)
def world_strides(shape: tuple[int, int, int], axis: int, sign: int) -> tuple[int, int, int, int]:
    """(base, sw, su, sv): face node (w, u, v) of the face (``axis``, ``sign``) of a lattice of
    ``shape`` is the world node base + w·sw + u·su + v·sv, counted in C order (``_kernel.
    to_face`` applied in NumPy to the node numbers: on the host, also under a trace)."""
    from ._kernel import to_face

    idx = to_face(np.arange(int(np.prod(shape))).reshape(shape), axis, sign)
    base = int(idx[0, 0, 0])
    steps = [int(idx[(1, 0, 0)] - base) if idx.shape[0] > 1 else 0,
             int(idx[(0, 1, 0)] - base) if idx.shape[1] > 1 else 0,
             int(idx[(0, 0, 1)] - base) if idx.shape[2] > 1 else 0]
    w, u, v = np.indices(idx.shape, sparse=True)
    if not np.array_equal(idx, base + w * steps[0] + u * steps[1] + v * steps[2]):
        raise AssertionError("to_face is not an axis permutation with flips")
    return (base, *steps)
