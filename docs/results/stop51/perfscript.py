"""The events of a `perf script` text dump, shared by pf.py and sc.py (stop 50's tl.py has
its own copy of the same parser)."""
import re

PAT = re.compile(r'^\s*(\S.*?)\s+(\d+)\s+\[(\d+)\]\s+([\d.]+):\s+(\S+):\s*(.*)$')


def events(path):
    """(time µs, pid, comm, event name, the rest of the line, cpu) for each event line."""
    out = []
    for line in open(path):
        m = PAT.match(line)
        if m:
            comm, pid, cpu, ts, name, rest = m.groups()
            out.append((float(ts) * 1e6, int(pid), comm, name, rest, int(cpu)))
    return out
