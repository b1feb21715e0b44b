// Cost of breaking copy-on-write in a fork child on this host: the child locks on fault,
// then breaks N resident pages (MADV_POPULATE_WRITE over one run, or one write per page),
// timed inside the child; reported through a pipe. SCHED_RR 60, pinned to CPU 1.
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <time.h>
#include <sched.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/wait.h>
#ifndef MADV_POPULATE_WRITE
#define MADV_POPULATE_WRITE 23
#endif
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(int argc,char**argv){
  int pages=atoi(argv[1]); int mode=atoi(argv[2]); int scattered=argc>3?atoi(argv[3]):0;
  cpu_set_t s; CPU_ZERO(&s); CPU_SET(1,&s); sched_setaffinity(0,sizeof s,&s);
  struct sched_param p={.sched_priority=60}; sched_setscheduler(0,SCHED_RR,&p);
  mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT);
  // scattered: each page in its own mapping (as an allocator's groups are)
  char *base[64];
  if(scattered){ for(int i=0;i<pages;i++){ base[i]=mmap(0,4096,PROT_READ|PROT_WRITE,MAP_PRIVATE|MAP_ANONYMOUS,-1,0); base[i][0]=1; } }
  else { base[0]=mmap(0,4096*pages,PROT_READ|PROT_WRITE,MAP_PRIVATE|MAP_ANONYMOUS,-1,0); for(int i=0;i<pages;i++) base[0][i*4096]=1; }
  signal(SIGCHLD,SIG_IGN);
  int N=300; double t[N]; int fd[2]; pipe(fd);
  for(int i=0;i<N;i++){
    pid_t c=fork();
    if(!c){
      double st=now();
      if(mode==1) mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT);
      if(scattered){ for(int k=0;k<pages;k++){ if(mode==2) base[k][0]++; else madvise(base[k],4096,MADV_POPULATE_WRITE);} }
      else if(mode==2){ for(int k=0;k<pages;k++) base[0][k*4096]++; }
      else madvise(base[0],4096*pages,MADV_POPULATE_WRITE);
      double d=now()-st; write(fd[1],&d,sizeof d); _exit(0);
    }
    read(fd[0],&t[i],sizeof(double)); usleep(1000);
  }
  qsort(t,N,sizeof(double),cmp);
  printf("pages=%2d mode=%d scattered=%d: child median %.1f us p90 %.1f\n",pages,mode,scattered,t[N/2],t[N*9/10]);
}
