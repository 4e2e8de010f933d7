"""Shared by the disk-full tests: a CLI run whose disk takes a given number of bytes, then is full."""

#: ``python -c FAIL_AFTER BYTES gesturedb-args...``: os.pwrite refuses with ENOSPC once BYTES are written
FAIL_AFTER = """\
import errno, os, sys
budget = [int(sys.argv[1])]
real = os.pwrite
def pwrite(fd, data, offset):  # the disk takes int(argv[1]) bytes, then is full
    n = min(len(data), budget[0])
    if n == 0:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    budget[0] -= n
    return real(fd, memoryview(data)[:n], offset)
os.pwrite = pwrite
from gesturedb.cli.main import main
sys.exit(main(sys.argv[2:]))
"""
