"""What a fit writes at its end, after the last step: the ranked materials (materials.json, the
err(k) plot and the material sheet), the envmap, the residual of novel views (VQ-NeRF Sec. 4),
the loss plot and fit.json."""

from __future__ import annotations

from vq_mitsuba.engine.plots import plot_err_k, plot_history
from vq_mitsuba.engine.trainer import Trainer
from vq_mitsuba.errors import warn
from vq_mitsuba.run.run_dir import RunDir


def write_products(trainer: Trainer, summary: dict) -> None:
    """Rank the codewords (when the discrete branch ran), fit the residual of novel views
    (`residual.iterations`) and write the run's results; `summary` becomes fit.json."""
    from vq_mitsuba.render.sheet import write_material_sheet

    run, cfg, model, env = trainer.run, trainer.cfg, trainer.model, trainer.envmap().detach()
    if model.discrete_on:
        info = model.rank_materials(trainer.data)
        trainer.checkpoint(summary["seconds"])  # with the ranked codebook and M
        run.write_materials(info)
        run.write_file(RunDir.ERR_PLOT, lambda path: plot_err_k(info["err_k"], info["num_materials"],
                                                                 info["epsilon"], path))
        run.write_file(RunDir.SHEET, lambda path: write_material_sheet(
            info["materials"], env.cpu().numpy(), trainer.capture.envmap_to_world, path))
    elif cfg.vq.enabled:
        warn("the fit ended before the discrete branch started (vq.warmup_frac); "
             "no materials.json was written")
    run.write_envmap(env.cpu().numpy())
    if cfg.residual.iterations > 0:  # VQ-NeRF Sec. 4: materials and light frozen from here
        summary["residual"] = model.fit_residual(run, trainer.data, trainer.step)
    run.write_file(RunDir.LOSS_PLOT, lambda path: plot_history(trainer.history, path))
    run.write_fit_summary(summary)
