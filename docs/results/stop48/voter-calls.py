import re, sys, statistics as st
pat = re.compile(r'^\s*(\S.*?)\s+(\d+)\s+\[(\d+)\]\s+([\d.]+):\s+(\S+):\s*(.*)$')
ev=[]
for line in open(sys.argv[1]):
    m=pat.match(line)
    if m: c,p,cpu,ts,n,r=m.groups(); ev.append((float(ts)*1e6,int(p),c,n,r))
names={0:'read',1:'write',3:'close',5:'fstat',16:'ioctl',17:'pread',19:'readv',20:'writev',14:'rt_sigprocmask',44:'sendto',45:'recvfrom',46:'sendmsg',47:'recvmsg',43:'accept',288:'accept4',232:'epoll_wait',281:'epoll_pwait',441:'epoll_pwait2',424:'pidfd_send_signal',62:'kill',61:'wait4',247:'waitid',203:'sched_setaffinity',314:'sched_setattr',144:'sched_setscheduler',142:'sched_setparam',228:'clock_gettime',7:'poll',271:'ppoll',72:'fcntl',54:'setsockopt',434:'pidfd_open',51:'getsockname',53:'socketpair',293:'pipe2',33:'dup2',292:'dup3',230:'clock_nanosleep',35:'nanosleep',286:'timerfd_settime',257:'openat'}
K=int(sys.argv[2]) if len(sys.argv)>2 else 3
idx=[i for i,e in enumerate(ev) if e[3]=='raw_syscalls:sys_enter' and 'voter' in e[2] and e[4].startswith('NR 424 ')]
print(len(idx),'RESTARTs')
for i in idx[K:K+1]:
    vp=ev[i][1]; t0=ev[i][0]
    for j in range(max(0,i-60), min(len(ev),i+400)):
        t,p,c,n,r=ev[j]
        if p==vp and n=='raw_syscalls:sys_enter':
            nr=int(re.search(r'NR (\d+)',r).group(1)); print("%8.1f voter %s"%(t-t0,names.get(nr,nr)))
        elif n=='sched:sched_process_exit' or (n=='raw_syscalls:sys_enter' and r.startswith('NR 44 ') and 'ballast' in c):
            print("%8.1f %s %d %s"%(t-t0,c,p,n))
