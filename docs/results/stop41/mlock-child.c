// stop 41: the cost of relocking a fork child (docs/results.md, "Where a restart's time goes here").
// gcc -O2 -o mlock-child mlock-child.c && taskset -c 1 chrt -r 50 ./mlock-child MODE KIB
// MODE 1: mlockall(MCL_CURRENT | MCL_ONFAULT); 2: mlock2 of one page (MLOCK_ONFAULT); 3: mlockall(MCL_FUTURE | MCL_ONFAULT).
// KIB: how much memory the parent has written (and locked) before it forks, 200 times.
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <time.h>
#include <string.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
int main(int argc,char**argv){
  int mode = atoi(argv[1]); size_t sz = atol(argv[2])*1024; int n=200;
  mlockall(MCL_CURRENT|MCL_FUTURE);
  char *m = malloc(sz); memset(m,1,sz);
  static char page[4096] __attribute__((aligned(4096)));
  double *t=calloc(n,sizeof(double));
  for(int i=0;i<n;i++){
    int p[2]; pipe(p);
    pid_t c=fork();
    if(!c){ double s=now();
      if(mode==1) mlockall(MCL_CURRENT|MCL_ONFAULT);
      if(mode==2) mlock2(page,4096,MLOCK_ONFAULT);
      if(mode==3) { mlockall(MCL_FUTURE|MCL_ONFAULT); }
      double e=now(); double d=e-s; write(p[1],&d,sizeof d); _exit(0);}
    double d; read(p[0],&d,sizeof d); t[i]=d; waitpid(c,0,0); close(p[0]); close(p[1]);
    usleep(2000);
  }
  for(int i=0;i<n;i++)for(int j=i+1;j<n;j++)if(t[j]<t[i]){double x=t[i];t[i]=t[j];t[j]=x;}
  printf("mode %d size %zuK: median %.1f us p90 %.1f\n", mode, sz/1024, t[n/2], t[n*9/10]);
}
