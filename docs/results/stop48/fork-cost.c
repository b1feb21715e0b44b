#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <time.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/wait.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(int argc,char**argv){
  int lock=atoi(argv[1]), vmas=atoi(argv[2]);
  if(lock==1) mlockall(MCL_CURRENT|MCL_FUTURE);
  if(lock==2) mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT);
  for(int i=0;i<vmas;i++){char*p=mmap(0,4096*(i+2),i%2?PROT_READ:PROT_READ|PROT_WRITE,MAP_PRIVATE|MAP_ANONYMOUS,-1,0); if(!(i%2))p[0]=1;}
  signal(SIGCHLD,SIG_IGN);
  int N=400; double t[N];
  for(int i=0;i<N;i++){double s=now(); pid_t c=fork(); if(!c)_exit(0); t[i]=now()-s; usleep(2000);}
  qsort(t,N,sizeof(double),cmp);
  printf("lock=%d vmas+%d: fork in parent median %.1f p90 %.1f\n",lock,vmas,t[N/2],t[N*9/10]);
}
