"""A simulator that talks a lot: writes ``argv[1]`` bytes in lines to standard output and a tenth
of that to standard error, then its last line, and exits 0
(``tests/drivers/sim/test_process.py``)."""
import sys

size = int(sys.argv[1])
line = "x" * 99 + "\n"
for _ in range(size // len(line)):
    sys.stdout.write(line)
for _ in range(size // len(line) // 10):
    sys.stderr.write(line)
sys.stdout.write("chatty: done\n")
