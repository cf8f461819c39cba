"""`python -m pipeline.bracket`: the bracket stage (:mod:`pipeline.bracket.stage`)."""

from pipeline.bracket.stage import main

if __name__ == "__main__":
    main()
