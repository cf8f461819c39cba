"""`python -m pipeline.experiments experiment=<id>` (`-m 'experiment=glob(*)'` runs them all)."""

from pipeline.cli import stage_main

main = stage_main("experiments", run="pipeline.experiments.stage:run", check="pipeline.experiments.checks:check")

if __name__ == "__main__":
    main()
