"""Sensor benchmark: sustained DCA1000 UDP ingest without loss, and the MMWCAS capture read rate.
Writes ``sensors.json`` to the output folder.

    python -m benchmarks.bench_sensors --out benchmarks/results [--quick]

UDP ingest: an emulated board in a second process streams MMWCAS-shaped frames (12 chirps x
16 RX x 256 samples, 196,608 bytes) over loopback at a set rate; the host receives, assembles
and decodes them to complex (n_tx, n_rx, N) frames. The rate is raised until frames are lost;
the figure is the highest rate with none lost. For scale: the paper's radar produces 2 MB/s
(one such frame per 100 ms); a DCA1000 on gigabit Ethernet tops out near 120 MB/s.

Capture read: a capture folder in TI's layout is written to a temporary folder (so it is in the
page cache: this measures the reader, not the disk), then read frame by frame, raw and as the
86 virtual channels of a scan.

DCA1000 files: the same MMWCAS-shaped frames written as mmWave Studio's raw ``adc_data.bin``,
the CLI's reordered form and its sequence-number records (one lost packet), read into decoded
frames by ``Dca1000FileCapture`` (``--only dca1000_files`` runs this part alone and updates
``sensors.json`` in place).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tempfile
import time
from pathlib import Path

import numpy as np

from twinfocus.radar.fmcw import Chirp
from twinfocus.sensors.dca1000 import Dca1000, RawFrameLayout
from twinfocus.sensors.emulators.mmwcas_capture import write_mmwcas_capture
from twinfocus.sensors.frames import frame_to_virtual_channels
from twinfocus.sensors.ti_mmwcas import MmwcasCapture, MmwcasConfig

LAYOUT = RawFrameLayout(256, 16, tuple(range(12)), 1, 12)


def _sender(addr, rate, n_frames, ready):
    from twinfocus.sensors.emulators.fake_dca1000 import FakeDca1000

    frame = np.random.default_rng(0).integers(-2000, 2000, LAYOUT.frame_values, dtype=np.int16).tobytes()
    with FakeDca1000(
        LAYOUT,
        frame_source=lambda k, lay: frame,
        host_data_addr=tuple(addr),
        frame_period_s=None,
        rate_bytes_per_s=rate,
        n_frames=n_frames,
    ) as board:
        ready.wait(5.0)
        board.start_streaming()
        board.done.wait(60.0)


def ingest_run(rate_mb_s: float, seconds: float) -> dict:
    rate = rate_mb_s * 1e6
    n_frames = max(20, int(rate * seconds / LAYOUT.frame_bytes))
    ctx = mp.get_context("fork")
    ready = ctx.Event()
    with Dca1000(
        board_addr=("127.0.0.1", 9), host_ip="127.0.0.1", config_port=0, data_port=0, recv_buffer_bytes=32 << 20
    ) as host:
        proc = ctx.Process(target=_sender, args=(host.data_addr, rate, n_frames, ready), daemon=True)
        proc.start()
        ready.set()
        t0 = None
        got = bad = 0
        for fr in host.frames(LAYOUT, max_frames=n_frames, idle_timeout_s=1.0, flush_after_s=0.3):
            if t0 is None:
                t0 = time.perf_counter()
            got += 1
            bad += not fr.flags.usable
        elapsed = time.perf_counter() - (t0 or time.perf_counter())
        proc.join(10.0)
        if proc.is_alive():
            proc.terminate()
            proc.join()
        st = host.stats
    good = got - bad
    return {
        "offered_MB_per_s": rate_mb_s,
        "frames_sent": n_frames,
        "frames_received_intact": good,
        "frames_damaged_or_lost": n_frames - good,
        "lost_bytes": st.lost_bytes,
        "ingest_MB_per_s": good * LAYOUT.frame_bytes / elapsed / 1e6 if elapsed > 0 else 0.0,
        "elapsed_s": elapsed,
    }


def bench_ingest(quick: bool) -> dict:
    rows = []
    best = 0.0
    for rate in [10, 40, 160] if quick else [10, 20, 40, 60, 80, 120, 160, 240, 320]:
        row = ingest_run(rate, 1.0 if quick else 2.0)
        rows.append(row)
        print(
            f"  UDP {rate:5.0f} MB/s offered: {row['frames_received_intact']}/{row['frames_sent']} intact, "
            f"ingest {row['ingest_MB_per_s']:.1f} MB/s"
        )
        if row["frames_damaged_or_lost"] == 0:
            best = max(best, row["ingest_MB_per_s"])
        else:
            break
    return {"frame_bytes": LAYOUT.frame_bytes, "runs": rows, "max_lossless_ingest_MB_per_s": best}


def bench_capture_read(quick: bool) -> dict:
    cfg = MmwcasConfig(chirp=Chirp())
    n = 60 if quick else 200
    rng = np.random.default_rng(1)
    iq = rng.integers(-2000, 2000, size=(n, 12, 16, 256, 2), dtype=np.int16)
    with tempfile.TemporaryDirectory() as d:
        write_mmwcas_capture(d, iq, np.arange(n) * 100_000_000, cfg)
        raw_bytes = 4 * n * cfg.device_frame_bytes
        best_raw = best_frames = best_virtual = np.inf
        for _ in range(2):
            with MmwcasCapture(d, cfg) as cap:
                t = time.perf_counter()
                for i in range(len(cap)):
                    cap.read_raw(i)
                best_raw = min(best_raw, time.perf_counter() - t)
                t = time.perf_counter()
                for _fr in cap.frames():
                    pass
                best_frames = min(best_frames, time.perf_counter() - t)
                t = time.perf_counter()
                for fr in cap.frames():
                    frame_to_virtual_channels(fr.data, cfg.chirp, 0.6)
                best_virtual = min(best_virtual, time.perf_counter() - t)
    out = {
        "frames": n,
        "bytes": raw_bytes,
        "raw_read_MB_per_s": raw_bytes / best_raw / 1e6,
        "decoded_frames_per_s": n / best_frames,
        "decoded_MB_per_s": raw_bytes / best_frames / 1e6,
        "virtual_channels_frames_per_s": n / best_virtual,
    }
    print(
        f"  capture read: raw {out['raw_read_MB_per_s']:.0f} MB/s, decoded {out['decoded_frames_per_s']:.0f} frames/s "
        f"({out['decoded_MB_per_s']:.0f} MB/s), to virtual channels {out['virtual_channels_frames_per_s']:.0f} frames/s"
    )
    return out


def bench_dca1000_files(quick: bool) -> dict:
    import struct

    from twinfocus.sensors.dca1000_files import CliCaptureSettings, Dca1000FileCapture

    n = 40 if quick else 150
    stream = np.random.default_rng(2).integers(-2000, 2000, n * LAYOUT.frame_values, dtype=np.int16)
    forms = {
        "raw": stream.tobytes(),
        "reordered": stream.reshape(-1, 4)[:, [0, 2, 1, 3]].tobytes(),  # I0 I1 Q0 Q1 -> I0 Q0 I1 Q1
    }
    raw = forms["raw"]
    recs = []
    for k, start in enumerate(range(0, len(raw), 1456)):
        if k != 7:  # one lost packet
            payload = raw[start : start + 1456]
            recs.append(struct.pack("<II", k + 1, len(payload)) + start.to_bytes(6, "little") + payload)
    forms["records"] = b"".join(recs)
    out = {"frames": n, "frame_bytes": LAYOUT.frame_bytes}
    with tempfile.TemporaryDirectory() as d:
        for name, data in forms.items():
            path = Path(d) / f"{name}.bin"
            path.write_bytes(data)
            settings = CliCaptureSettings(reorder=name == "reordered")
            best = np.inf
            for _ in range(2):
                t = time.perf_counter()
                cap = Dca1000FileCapture(path, LAYOUT, 0.1, name, settings)
                best = min(best, time.perf_counter() - t)
            assert len(cap.frames) == n, (name, len(cap.frames), cap.warnings)
            out[name] = {
                "decoded_frames_per_s": n / best,
                "MB_per_s": len(data) / best / 1e6,
                "frames_zero_filled": cap.stats.frames_zero_filled,
            }
            print(f"  DCA1000 file '{name}': {n / best:.0f} frames/s ({len(data) / best / 1e6:.0f} MB/s)")
    return out


def main(out_dir, quick: bool = False, only: str | None = None) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    parts = {"udp_ingest": bench_ingest, "capture_read": bench_capture_read, "dca1000_files": bench_dca1000_files}
    path = out_dir / "sensors.json"
    if only:
        result = json.loads(path.read_text()) if path.is_file() else {}
        result[only] = parts[only](quick)
    else:
        result = {k: f(quick) for k, f in parts.items()}
    path.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--only", choices=["udp_ingest", "capture_read", "dca1000_files"], help="run one part, update sensors.json"
    )
    a = ap.parse_args()
    main(a.out, a.quick, a.only)
