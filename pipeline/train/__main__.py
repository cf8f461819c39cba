"""`python -m pipeline.train [data=clean] [model=paper] [trainer=paper] ...`"""

from pipeline.cli import stage_main


@stage_main("train")
def main(cfg):
    from pipeline.train.stage import run

    return run(cfg)


if __name__ == "__main__":
    main()
