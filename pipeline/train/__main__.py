"""`python -m pipeline.train [data=clean] [model=paper] [trainer=gpu] [logger=tensorboard] ...`

With `optimized_metric` set (`hparams_search=...`), the job returns that metric of the trained map (e.g. its
best validation MAE) for Hydra's sweeper to minimise.
"""

from pipeline.cli import stage_main

main = stage_main("train", run="pipeline.train.stage:job", check="pipeline.train.checks:check")

if __name__ == "__main__":
    main()
