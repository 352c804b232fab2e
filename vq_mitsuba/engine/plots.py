"""The plots a fit writes: training curves and the err_k curve with M marked."""

from __future__ import annotations

from pathlib import Path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_err_k(errs: list[float], chosen: int, eps: float, path: Path) -> None:
    plt = _pyplot()
    ks = list(range(1, len(errs) + 1))
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    ax.plot(ks, errs, "o-")
    ax.axvline(chosen, color="tab:red", linestyle="--", label=f"M = {chosen}")
    ax.axhspan(min(errs), min(errs) + eps, color="tab:green", alpha=0.15, label=f"min + epsilon ({eps:g})")
    ax.set_xlabel("k (first k ranked codewords)")
    ax.set_ylabel("err_k")
    ax.set_title("material count by dropout ranking")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_history(history: list[dict], path: Path) -> None:
    """The training loss and PSNR against the step (a fit that ended before its first logged step,
    e.g. at its time limit, has empty axes)."""
    plt = _pyplot()
    steps = [h["step"] for h in history]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    ax[0].semilogy(steps, [h["loss"] for h in history])
    ax[0].set_xlabel("iteration"); ax[0].set_ylabel("loss"); ax[0].set_title("training loss")
    ax[1].plot(steps, [h["psnr"] for h in history])
    ax[1].set_xlabel("iteration"); ax[1].set_ylabel("PSNR (dB, sRGB)"); ax[1].set_title("training-batch PSNR")
    if not history:
        for a in ax:
            a.text(0.5, 0.5, "no step logged", ha="center", va="center", transform=a.transAxes)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
