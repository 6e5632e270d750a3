from lensfit.cli import run

run()
