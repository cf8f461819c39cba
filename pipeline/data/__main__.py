"""`python -m pipeline.data data=<recipe>`: render a tracked camera dataset (see pipeline.data.stage)."""

from pipeline.cli import stage_main

main = stage_main("data", run="pipeline.data.stage:run", check="pipeline.data.plan:check")

if __name__ == "__main__":
    main()
