#!/usr/bin/env python3
# per fork of a ballast replica: the child's user page faults from the fork to Ready (its 2nd sendto),
# by phase (before Hello / Hello..recvmsg / recvmsg..Ready) and kind (error code)
import re, sys, statistics as st, collections
from perfscript import events
ev = events(sys.argv[1])
def kind(ec):
    ec=int(ec,16)
    if ec & 0x10: return 'exec'
    if ec & 2: return 'cow' if ec & 1 else 'wr-new'
    return 'rd-prot' if ec & 1 else 'read'
rows=[]; kinds=collections.Counter(); addrs=collections.Counter()
for i,(t,pid,comm,name,rest,_cpu) in enumerate(ev):
    if name!='sched:sched_process_fork' or 'ballast' not in comm: continue
    child=int(re.search(r'child_pid=(\d+)',rest).group(1))
    d={'fork':t,'pf':[]}; phase='pre'
    for j in range(i+1,min(len(ev),i+6000)):
        tj,p,c,n,r,_=ev[j]
        if p!=child: continue
        if n=='syscalls:sys_enter_sendto':
            if 'hello' not in d: d['hello']=tj; phase='walk'
            else: d['ready']=tj; break
        elif n=='syscalls:sys_enter_recvmsg': d.setdefault('rv0',tj); phase='recv'
        elif n=='exceptions:page_fault_user':
            a=re.search(r'address=(0x[0-9a-f]+)',r).group(1); ec=re.search(r'error_code=(0x[0-9a-f]+)',r).group(1)
            ip=re.search(r'ip=(0x[0-9a-f]+)',r).group(1)
            d['pf'].append((tj-t,phase,kind(ec),a,ip))
    if 'ready' in d: rows.append(d)
print(len(rows),'forks')
n=[len(r['pf']) for r in rows]; print('faults per child fork->Ready: median',st.median(n),'min',min(n),'max',max(n))
for ph in ['pre','walk','recv']:
    c=collections.Counter()
    for r in rows:
        for f in r['pf']:
            if f[1]==ph: c[f[2]]+=1
    print(' ',ph,{k:round(v/len(rows),1) for k,v in c.items()})
# one example child
r=rows[len(rows)//2]
print('example: hello',round(r['hello']-r['fork'],1),'rv0',round(r.get('rv0',0)-r['fork'],1),'ready',round(r['ready']-r['fork'],1))
for f in r['pf']: print('  %7.1f %-5s %-7s addr %s ip %s'%f)
