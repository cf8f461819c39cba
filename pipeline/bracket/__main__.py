"""`python -m pipeline.bracket`: the bracket stage (:mod:`pipeline.bracket.stage`)."""

from pipeline.cli import stage_main

main = stage_main("bracket", run="pipeline.bracket.stage:run", check="pipeline.bracket.stage:check")

if __name__ == "__main__":
    main()
