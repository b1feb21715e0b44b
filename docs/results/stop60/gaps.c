#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <stdint.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include <sched.h>
#include <fcntl.h>
#include <sys/syscall.h>
#include <linux/perf_event.h>
static uint64_t ns(clockid_t c){struct timespec t; clock_gettime(c,&t); return t.tv_sec*1000000000ull+t.tv_nsec;}
static void schedstat(int fd, uint64_t *run, uint64_t *wait){char b[128]; int n=pread(fd,b,127,0); b[n>0?n:0]=0; sscanf(b,"%lu %lu",run,wait);}
int main(int argc,char**argv){
  int cpu=atoi(argv[1]); double secs=atof(argv[2]); int prio=atoi(argv[3]);
  cpu_set_t s; CPU_ZERO(&s); CPU_SET(cpu,&s); sched_setaffinity(0,sizeof s,&s);
  if(prio){struct sched_param p={.sched_priority=prio}; if(sched_setscheduler(0,SCHED_RR,&p)) perror("rr");}
  struct perf_event_attr a; memset(&a,0,sizeof a); a.type=PERF_TYPE_SOFTWARE; a.size=sizeof a; a.config=PERF_COUNT_SW_TASK_CLOCK; a.exclude_kernel=1; a.exclude_hv=1;
  int pf=syscall(SYS_perf_event_open,&a,0,-1,-1,0); if(pf<0){perror("perf");return 1;}
  int ss=open("/proc/thread-self/schedstat",O_RDONLY);
  uint64_t end=ns(CLOCK_MONOTONIC)+(uint64_t)(secs*1e9);
  uint64_t m0=ns(CLOCK_MONOTONIC), c0=ns(CLOCK_THREAD_CPUTIME_ID), p0; read(pf,&p0,8);
  uint64_t r0,w0; schedstat(ss,&r0,&w0);
  long ngaps=0;
  while(1){
    uint64_t m=ns(CLOCK_MONOTONIC), c=ns(CLOCK_THREAD_CPUTIME_ID), p; read(pf,&p,8);
    if(m-m0>30000){ uint64_t r,w; schedstat(ss,&r,&w);
      printf("gap %8.1f us  cputime %8.1f  perf %8.1f  booked-wait %8.1f\n",(m-m0)/1e3,(c-c0)/1e3,(p-p0)/1e3,(w-w0)/1e3); ngaps++; w0=w; m=ns(CLOCK_MONOTONIC); c=ns(CLOCK_THREAD_CPUTIME_ID); read(pf,&p,8);}
    else { uint64_t r,w; (void)r; w=w0; (void)w; }
    m0=m;c0=c;p0=p; if(m>end)break;
  }
  fprintf(stderr,"gaps %ld\n",ngaps);
}
