"""`python -m pipeline.train [data=clean] [model=paper] [trainer=gpu] [logger=tensorboard] ...`

With `optimized_metric` set (`hparams_search=...`), the job returns that metric of the trained map (e.g. its
best validation MAE) for Hydra's sweeper to minimise.
"""

from pipeline.cli import stage_main


@stage_main("train")
def main(cfg):
    from pipeline.train.stage import objective, run

    out = run(cfg)
    return objective(out, cfg.get("optimized_metric"))


if __name__ == "__main__":
    main()
