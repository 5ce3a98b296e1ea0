"""A user effect in a few lines, fitted and diagnosed like the built-in ones (docs/writing_an_effect.md).

Run:  python examples/02_write_an_effect.py
The log hides a constant 3 cm range offset; `range_offset` below is written from scratch,
registered, found by diagnose and fitted, and the script prints the NLL curve over iterations.
"""

import argparse

import mi_lidar  # noqa: F401
from mi_lidar.core.effects import Effect, register_effect
from mi_lidar.core.params import ParamSpec
from mi_lidar.loop import diagnose
from mi_lidar.loop.demo import make_hidden_log, print_plain


@register_effect
class RangeOffset(Effect):
    """Constant range offset ``z = r + offset`` (m), differentiable."""

    name = "range_offset"
    specs = {"offset": ParamSpec(0.0, "m", "added to every return", lower=-1.0, upper=1.0)}
    fit_scales = {"offset": 0.01}  # typical size: the fitter's step unit

    def modify_segment(self, seg, rays):
        return seg.with_(mean=seg.mean + self["offset"], lo=seg.lo + self["offset"], hi=seg.hi + self["offset"])


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args()
    scene, model, log = make_hidden_log("range_offset(offset=0.03)")
    d = diagnose(log, scene, model, candidates=["range_offset", "range_noise", "outliers"], rounds=1, steps=100)
    print_plain(d.summary)
    print(
        "fitted on every ray (the model diagnose returns):",
        {k: [round(float(x), 5) for x in v] for k, v in d.parameters.items()},
    )
    best = d.rounds[0][0]
    print(
        "screening fit, mean log-likelihood per ray over iterations:",
        " ".join(f"{x:.3f}" for x in best.history[:: max(1, len(best.history) // 10)]),
    )
