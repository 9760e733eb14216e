from dqpose.cli import run

run()
