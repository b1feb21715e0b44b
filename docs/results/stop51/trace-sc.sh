#!/bin/bash
exec 4>/dev/cpu_dma_latency; printf "\0\0\0\0" >&4
perf record -q -a -o $3.data -e sched:sched_process_fork -e raw_syscalls:sys_enter -e raw_syscalls:sys_exit -e exceptions:page_fault_user -e sched:sched_switch -- \
  $1 restart --setup rr-pinned --cpu-idle poll --size ${SIZE:-4k} --count ${COUNT:-30} --json --quiet --component-dir $2 2>/dev/null | grep '^{'
perf script -i $3.data > $3.txt 2>/dev/null
