"""`python -m pipeline.experiments experiment=<id>` (`-m 'experiment=glob(*)'` runs them all)."""

from pipeline.cli import stage_main
from pipeline.experiments.stage import check


@stage_main("experiments", check=check)
def main(cfg):
    from pipeline.experiments.stage import run

    return run(cfg)


if __name__ == "__main__":
    main()
