"""`python -m pipeline.train [data=clean] [model=paper] [trainer=gpu] [logger=tensorboard] ...`

With `optimized_metric` set (`hparams_search=...`), the job returns that metric of the trained map (e.g. its
best validation MAE) for Hydra's sweeper to minimise.
"""

from pipeline.cli import stage_main


def check(cfg) -> None:
    """Preflight: every config value, and the dataset this config trains on (by id) must be built."""
    from pipeline.data import open_dataset
    from pipeline.lineage import train_dataset_id
    from pipeline.train.stage import check_config

    check_config(cfg)
    name, id_ = train_dataset_id(cfg)
    open_dataset(f"{name}-{id_}", datasets_dir=cfg.paths.datasets_dir)


@stage_main("train", check=check)
def main(cfg):
    from pipeline.train.stage import objective, run

    out = run(cfg)
    return objective(out, cfg.get("optimized_metric"))


if __name__ == "__main__":
    main()
