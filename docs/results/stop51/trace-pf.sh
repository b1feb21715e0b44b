#!/bin/bash
# trace-pf.sh BENCH COMPDIR OUT: 4 KiB restarts with every user page fault, fork, and the child's handshake calls
exec 4>/dev/cpu_dma_latency; printf "\0\0\0\0" >&4
perf record -q -a -o $3.data -e sched:sched_process_fork -e exceptions:page_fault_user \
  -e syscalls:sys_enter_sendto -e syscalls:sys_enter_recvmsg -e syscalls:sys_exit_recvmsg \
  -e syscalls:sys_enter_madvise -e syscalls:sys_enter_mincore -e syscalls:sys_exit_madvise -- \
  $1 restart --setup rr-pinned --cpu-idle poll --size ${SIZE:-4k} --count ${COUNT:-30} --json --quiet --component-dir $2 2>/dev/null | grep '^{'
perf script -i $3.data > $3.txt 2>/dev/null
