"""The chaos soak (`gwc soak`) and the private cell it and `gwc bench cell` run on.

plan.py draws everything random from the seed; cell.py starts, breaks, repairs and stops a private
cell; driver.py runs lots through it while faults strike, then judges what is left.
"""
