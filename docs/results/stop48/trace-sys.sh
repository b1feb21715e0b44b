#!/bin/bash
# trace.sh VARIANT OUT: perf record of restarts at 4 KiB with few tracepoints
v=$1; out=$2
exec 4>/dev/cpu_dma_latency; printf "\0\0\0\0" >&4
perf record -q -a -o $out.data -e sched:sched_process_fork -e sched:sched_switch -e signal:signal_deliver -e raw_syscalls:sys_enter -e raw_syscalls:sys_exit \
  -e syscalls:sys_enter_sendto \
  -e syscalls:sys_enter_pidfd_send_signal -- \
  /tmp/s48/$v/s3res-bench restart --setup rr-pinned --cpu-idle poll --size 4k --count ${COUNT:-30} --json --quiet --component-dir /tmp/s48/$v/comp 2>/dev/null | grep '^{'
perf script -i $out.data > $out.txt 2>/dev/null
