"""`python -m pipeline.certify [maps=<ref>] [cell=0.25] [kappas=[0,1]] [tolerance=1] [max_depth=1] ...`

`model=<ref>` is accepted as an alias of `maps=<ref>` (as in the errormap stage).
"""

import re
import sys

from pipeline.cli import stage_main

main = stage_main("certify", run="pipeline.certify.stage:run", check="pipeline.certify.checks:check")

if __name__ == "__main__":
    sys.argv = [sys.argv[0], *[re.sub(r"^model=", "maps=", a) for a in sys.argv[1:]]]
    main()
