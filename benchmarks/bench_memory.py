"""Benchmark: peak memory of ingest on a recording of more than 2 GB, measured, not extrapolated.

Makes the recording under ``--dir`` (default /tmp; free disk is checked first),
in two streaming steps, so that making it never holds more than one chunk:

1. the simulator writes a short cell (LR Mate-like, 3 targets x 2 poses) with
   large uncompressed images (``[camera] image = "raw"``, 2048 x 1536 by default);
2. that recording is played back ``K`` times into one MCAP file without chunk
   compression, each cycle shifted in time by the cycle's length plus 1 s
   (log and publish times, and the ``header.stamp`` of every image and joint
   state), until the file holds at least ``--gb`` GB: a long run in which the
   robot goes back to the same measuring poses ``K`` times. The robot
   description, the ``touchup`` metadata and any other message are written once.

Then ``vtcal run BIG --until touchups`` (ingest, detection of every image, the
touch-up stage) runs as a child process and its peak resident set size is
read from the kernel (``os.wait4`` rusage ``ru_maxrss`` of that child alone).
The same is done on the one-cycle recording: memory that does not grow with the
recording is flat between the two. Printed: sizes, images, times, throughput,
peak RSS of both runs and of this process (the generator). The big recording
and its run folder are deleted at the end (``--keep`` keeps them).

    python benchmarks/bench_memory.py [--gb 2.05] [--width 2048 --height 1536] [--dir /tmp]

Goal: ingest peak RSS under 1 GB on a >= 2 GB recording.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCENARIO = """\
name = "memory"
[robot]
name = "lrmate"
[camera]
width = {width}
height = {height}
image = "raw"
[targets]
count = 3
[poses]
per_target = 2
"""

#: topics whose messages are repeated every cycle (the rest is written once)
REPEATED = ("sensor_msgs/msg/Image", "sensor_msgs/msg/JointState")


def simulate(workdir: Path, width: int, height: int, seed: int) -> Path:
    """The one-cycle recording, written by the simulator (streaming)."""
    from pipeline.sim.scenario import load_scenario
    from pipeline.sim.simulator import write_recording

    toml = workdir / "memory.toml"
    toml.write_text(SCENARIO.format(width=width, height=height))
    out = workdir / "cycle.mcap"
    write_recording(load_scenario(toml), seed, out)
    return out


def shift_stamp(data: bytes, shift_ns: int) -> bytes:
    """A CDR message whose leading ``std_msgs/Header`` stamp is moved by ``shift_ns``.

    CDR layout: 4-byte encapsulation header (byte 1: 0 big, 1 little endian),
    then ``builtin_interfaces/Time`` ``int32 sec, uint32 nanosec``.
    """
    fmt = "<iI" if data[1] & 1 else ">iI"
    sec, nsec = struct.unpack_from(fmt, data, 4)
    t = sec * 1_000_000_000 + nsec + shift_ns
    return data[:4] + struct.pack(fmt, t // 1_000_000_000, t % 1_000_000_000) + data[12:]


def replay(src: Path, dst: Path, min_bytes: int) -> tuple[int, int]:
    """Write ``src`` again and again into ``dst`` (uncompressed) until it holds ``min_bytes``.

    Returns (cycles, images). Reads and writes one message at a time.
    """
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with src.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        t_first = summary.statistics.message_start_time
        t_last = summary.statistics.message_end_time
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
    period = t_last - t_first + 1_000_000_000
    cycles = images = 0
    with dst.open("wb") as out:
        w = Writer(out, chunk_size=8 << 20, compression=CompressionType.NONE)
        w.start(profile="ros2", library="vtcal bench_memory")
        for name, data in metadata:
            w.add_metadata(name, data)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        seq = 0
        while out.tell() < min_bytes:
            shift = cycles * period
            with src.open("rb") as f:
                for schema, channel, msg in make_reader(f).iter_messages(log_time_order=False):
                    repeated = schema is not None and schema.name in REPEATED
                    if cycles and not repeated:
                        continue
                    if schema is not None and schema.id not in schema_ids:
                        schema_ids[schema.id] = w.register_schema(
                            schema.name, schema.encoding, schema.data
                        )
                    if channel.id not in channel_ids:
                        channel_ids[channel.id] = w.register_channel(
                            channel.topic,
                            channel.message_encoding,
                            schema_ids.get(channel.schema_id, 0),
                            dict(channel.metadata),
                        )
                    data = shift_stamp(msg.data, shift) if repeated and shift else msg.data
                    w.add_message(
                        channel_ids[channel.id],
                        log_time=msg.log_time + shift,
                        data=data,
                        publish_time=msg.publish_time + shift,
                        sequence=seq,
                    )
                    seq += 1
                    images += schema is not None and schema.name == "sensor_msgs/msg/Image"
            cycles += 1
        w.finish()
    return cycles, images


def child(cmd: list[str]) -> tuple[float, float, float, str]:
    """Run ``cmd`` as a child; (wall s, peak RSS MB from ``wait4``, from ``VmHWM``, output).

    ``ru_maxrss`` of a child counts the memory of this process at the fork too
    (Linux keeps the larger of the two across ``exec``), so this process stays
    small: it imports neither the pipeline nor numpy. As an independent
    reading, the child's ``VmHWM`` (high-water mark of its own address space)
    is sampled from ``/proc`` every 50 ms; its last reading is a lower bound.
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    hwm = 0.0
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        status_file = Path(f"/proc/{proc.pid}/status")
        while True:
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            try:
                for line in status_file.read_text().splitlines():
                    if line.startswith("VmHWM:"):
                        hwm = max(hwm, int(line.split()[1]) / 1024.0)
            except (OSError, ValueError):
                pass
            time.sleep(0.05)
        proc.returncode = os.waitstatus_to_exitcode(status)
        dt = time.perf_counter() - t0
        log.seek(0)
        text = log.read().decode(errors="replace").strip()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:5])} ... exited {proc.returncode}: {text[-400:]}")
    return dt, ru.ru_maxrss / 1024.0, hwm, text


def ingest(rec: Path, out: Path) -> tuple[float, float, float, str]:
    """``vtcal run REC --until touchups`` as a child (see :func:`child`)."""
    cmd = [sys.executable, "-m", "pipeline", "run", str(rec), "--out", str(out)]
    return child([*cmd, "--until", "touchups", "--force", "-q"])


def generate(args: argparse.Namespace) -> None:
    """Child mode: simulate one cycle and replay it into the long run; print figures."""
    work = args.generate
    t0 = time.perf_counter()
    cycle = simulate(work, args.width, args.height, args.seed)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    cycles, n_images = replay(cycle, work / "long_run.mcap", int(args.gb * 1e9))
    t_rep = time.perf_counter() - t0
    print(f"{t_sim} {t_rep} {cycles} {n_images}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gb", type=float, default=2.05, help="recording size, GB (1e9 B)")
    ap.add_argument("--width", type=int, default=2048)
    ap.add_argument("--height", type=int, default=1536)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--dir", type=Path, default=Path("/tmp"), help="where to write it")
    ap.add_argument("--keep", action="store_true", help="keep the recordings and run folders")
    ap.add_argument("--generate", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.generate is not None:
        return generate(args)

    need = int(args.gb * 1e9)
    free = shutil.disk_usage(args.dir).free
    print(f"free disk under {args.dir}: {free / 1e9:.1f} GB (need about {need / 1e9 * 1.05:.1f})")
    if free < need * 1.2:
        raise SystemExit(f"{args.dir}: not enough free disk for a {args.gb} GB recording")
    print(f"cores {os.cpu_count()}, load average before {os.getloadavg()[0]:.2f}")
    work = Path(tempfile.mkdtemp(prefix="bench_memory_", dir=args.dir))
    try:
        gen = [sys.executable, __file__, "--generate", str(work), "--gb", str(args.gb)]
        gen += ["--width", str(args.width), "--height", str(args.height)]
        _, gen_rss, gen_hwm, text = child([*gen, "--seed", str(args.seed)])
        t_sim, t_rep, cyc, img = text.splitlines()[-1].split()
        t_sim_s, t_rep_s, cycles, n_images = float(t_sim), float(t_rep), int(cyc), int(img)
        cycle, big = work / "cycle.mcap", work / "long_run.mcap"
        size = big.stat().st_size
        print(
            f"one cycle: {cycle.stat().st_size / 1e6:.0f} MB (zstd chunks), simulated in "
            f"{t_sim_s:.1f} s; {args.width} x {args.height} raw mono8 images"
        )
        print(
            f"long run: {size / 1e9:.3f} GB uncompressed, {cycles} cycles, {n_images} images, "
            f"written in {t_rep_s:.1f} s ({size / 1e6 / t_rep_s:.0f} MB/s)"
        )
        print(f"generator peak RSS (simulation + replay): {gen_rss:.0f} MB (VmHWM {gen_hwm:.0f})")

        dt1, rss1, hwm1, _ = ingest(cycle, work / "run_cycle")
        dt2, rss2, hwm2, _ = ingest(big, work / "run_long")
        per = n_images // cycles
        print(
            f"vtcal run --until touchups, one cycle ({per} images): {dt1:.1f} s, "
            f"peak RSS {rss1:.0f} MB (VmHWM {hwm1:.0f})"
        )
        print(
            f"vtcal run --until touchups, {size / 1e9:.2f} GB ({n_images} images): {dt2:.1f} s "
            f"({n_images / dt2:.1f} images/s, {size / 1e6 / dt2:.0f} MB/s), "
            f"peak RSS {rss2:.0f} MB (VmHWM {hwm2:.0f})"
        )
        print(f"  peak RSS long / one cycle: x{rss2 / rss1:.2f} for x{cycles} the images")
        print(f"  goal: peak RSS < 1024 MB: {'met' if rss2 < 1024 else 'NOT met'}")
        own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        print(f"  (this benchmark process, counted in the children's ru_maxrss: {own:.0f} MB)")
        import pyarrow.parquet as pq

        n_rows = pq.read_metadata(work / "run_long" / "frames.parquet").num_rows
        n_tu = pq.read_metadata(work / "run_long" / "touchups.parquet").num_rows
        print(f"  artefacts: frames {n_rows} rows, touch-ups {n_tu} rows")
        print(f"load average after: {os.getloadavg()[0]:.2f}")
    finally:
        if args.keep:
            print(f"kept: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
