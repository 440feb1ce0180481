"""Are the calibration's stated errors the errors?

Flat fields 30x brighter and 30x darker than ``L_const`` through each preset's designed
rig, captured through a region of interest (its readout keeps up), calibrated with
:func:`asynhdr.calib.thresholds_from_flats`; each pixel's error (estimate less the
simulator's own threshold, :func:`asynhdr.simulate.draw_thresholds`) over its stated
error should be a standard normal: a standard deviation of 1, 0.27 % beyond 3.
"""

from __future__ import annotations

import argparse

import numpy as np

from asynhdr.calib import thresholds_from_flats
from asynhdr.design import default_rig
from asynhdr.scene import flat_field
from asynhdr.sensor.params import get_preset
from asynhdr.simulate import draw_thresholds, simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["davis346", "imx636"])
    ap.add_argument("--cycles", type=int, nargs="+", default=[4],
                    help="cycles per capture (the first is left out)")
    ap.add_argument("--size", type=int, nargs=2, default=[40, 30], metavar=("W", "H"))
    a = ap.parse_args()
    w, h = a.size
    print(f"{w}x{h} flats at 30x and 1/30x L_const, one capture each; error / stated error")
    print(f"{'preset':9} {'cycles':>6} {'pol':>4} {'rms error':>9} {'median stated':>13} "
          f"{'std z':>6} {'|z|>3':>7} {'|z|>10':>7} {'max |z|':>7}")
    for preset in a.presets:
        rig, sensor = default_rig(preset), get_preset(preset)
        roi = sensor.region_of_interest()
        rads = [rig.l_const * 30, rig.l_const / 30]
        c_on, c_off = draw_thresholds(sensor, width=w, height=h, rng=np.random.default_rng(7))
        for n in a.cycles:
            caps = [simulate(flat_field(width=w, height=h, radiance=r), rig=rig, sensor=roi,
                             n_cycles=n, rng=i, sensor_seed=7) for i, r in enumerate(rads)]
            cal = thresholds_from_flats(caps, radiance=rads, rig=rig, sensor=sensor)
            assert cal.c_on is not None and cal.c_off is not None
            assert cal.sigma_on is not None and cal.sigma_off is not None
            for pol, est, true, err in (("on", cal.c_on, c_on, cal.sigma_on),
                                        ("off", cal.c_off, c_off, cal.sigma_off)):
                e = (est - true).ravel()
                z = e / err.ravel()
                beyond3, beyond10 = (100 * np.mean(np.abs(z) > b) for b in (3, 10))
                print(f"{preset:9} {n:>6} {pol:>4} {np.sqrt(np.mean(e ** 2)):>9.4f} "
                      f"{np.median(err):>13.4f} {np.std(z):>6.2f} {beyond3:>6.2f}% "
                      f"{beyond10:>6.2f}% {np.abs(z).max():>7.1f}")


if __name__ == "__main__":
    main()
