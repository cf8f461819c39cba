"""`python -m pipeline.errormap [model=<name>] [occlusion_levels=[none,heavy]] [grid.step=0.5] ...`"""

from omegaconf import DictConfig

from pipeline.cli import stage_main
from pipeline.errormap.stage import run


@stage_main("errormap")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
