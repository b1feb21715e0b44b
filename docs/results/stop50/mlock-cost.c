#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#include <time.h>
#include <sched.h>
#include <signal.h>
#include <sys/mman.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(int argc,char**argv){
  int mode=atoi(argv[1]); int cpu=argc>2?atoi(argv[2]):1;
  cpu_set_t s; CPU_ZERO(&s); CPU_SET(cpu,&s); sched_setaffinity(0,sizeof s,&s);
  struct sched_param p={.sched_priority=60}; sched_setscheduler(0,SCHED_RR,&p);
  mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT);
  signal(SIGCHLD,SIG_IGN);
  int N=300; double t[N]; int fd[2]; pipe(fd);
  for(int i=0;i<N;i++){
    if(mode==0){ munlockall(); double st=now(); mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT); t[i]=now()-st; usleep(500); continue; }
    pid_t c=fork();
    if(!c){
      double st=now();
      if(mode==1) mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT);
      if(mode==2) mlockall(MCL_FUTURE|MCL_ONFAULT);
      if(mode==3) mlockall(MCL_CURRENT|MCL_FUTURE);
      if(mode==4) getppid();
      double d=now()-st; write(fd[1],&d,sizeof d); _exit(0);
    }
    read(fd[0],&t[i],sizeof(double)); usleep(1000);
  }
  qsort(t,N,sizeof(double),cmp);
  printf("mode=%d cpu=%d: median %.1f us p90 %.1f\n",mode,cpu,t[N/2],t[N*9/10]);
}
