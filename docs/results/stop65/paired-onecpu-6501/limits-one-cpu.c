// Physical-limit probes for the NMR middleware: pipe round trips, a minimal
// C fan-out voter (1..3 replicas), and fork+page-walk restart cost.
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <poll.h>
#include <time.h>
#include <signal.h>
#include <sys/prctl.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
static void pin(int c){cpu_set_t s;CPU_ZERO(&s);CPU_SET(0,&s);sched_setaffinity(0,sizeof s,&s);}
static int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
static void rd(int fd,char*b,int n){int g=0;while(g<n){int r=read(fd,b+g,n-g);if(r<=0)exit(1);g+=r;}}
// echo replica: read n bytes, write n bytes
static void echo(int in,int out,int n){char*b=malloc(n>0?n:1);for(;;){rd(in,b,n);write(out,b,n);}}
// fan-out voter between client pipes and r replicas
static void voter(int cin,int cout,int r,int n,int core){
  int to[3][2],fr[3][2];
  for(int i=0;i<r;i++){pipe(to[i]);pipe(fr[i]);if(!fork()){prctl(PR_SET_PDEATHSIG,SIGKILL);pin(core+1+i);echo(to[i][0],fr[i][1],n);}}
  char*b=malloc(n),*o[3];for(int i=0;i<r;i++)o[i]=malloc(n);
  for(;;){rd(cin,b,n);for(int i=0;i<r;i++)write(to[i][1],b,n);
    for(int i=0;i<r;i++)rd(fr[i][0],o[i],n);
    int w=0; if(r==3){ if(memcmp(o[0],o[1],n)&&!memcmp(o[1],o[2],n))w=1; }
    write(cout,o[w],n);}
}
int main(int argc,char**argv){
  int iters=getenv("ITERS")?atoi(getenv("ITERS")):20000; pin(0);
  int do_rt=argc<2||!strcmp(argv[1],"roundtrip"), do_fork=argc<2||!strcmp(argv[1],"fork");
  int sizes[]={8,4096};
  for(int si=0;do_rt&&si<2;si++){int n=sizes[si]; if(getenv("SIZE")&&n!=atoi(getenv("SIZE")))continue;
   for(int r=0;r<=3;r++){ if(getenv("LEVEL")&&r!=atoi(getenv("LEVEL")))continue; // r=0: no voter (NMR)
    int a[2],b[2];pipe(a);pipe(b);pid_t p=fork();
    if(!p){ prctl(PR_SET_PDEATHSIG,SIGKILL); if(r==0){pin(1);echo(a[0],b[1],n);} else voter(a[0],b[1],r,n,0);}
    pin(0);char*buf=calloc(1,n);double*t=malloc(sizeof(double)*iters);
    for(int i=0;i<1000;i++){write(a[1],buf,n);rd(b[0],buf,n);}
    for(int i=0;i<iters;i++){double s=now();write(a[1],buf,n);rd(b[0],buf,n);t[i]=now()-s;}
    qsort(t,iters,sizeof(double),cmp);
    printf("roundtrip size=%d replicas=%d median_us=%.2f p99_us=%.2f max_us=%.2f\n",n,r,t[iters/2],t[iters*99/100],t[iters-1]);
    kill(0,0); kill(p,9); // children of voter die on pipe EOF
    close(a[1]);close(b[0]);waitpid(p,0,0); while(waitpid(-1,0,WNOHANG)>0);
    usleep(20000);
   }}
  // fork + page walk restart cost
  long kbs[]={256,1024,8192,65536};
  for(int k=0;do_fork&&k<4;k++){long sz=kbs[k]*1024;char*m=malloc(sz);memset(m,1,sz);
    mlockall(MCL_CURRENT|MCL_FUTURE);
    int N=200;double*t=malloc(sizeof(double)*N);
    for(int i=0;i<N;i++){int pp[2];pipe(pp);double s=now();pid_t c=fork();
      if(!c){long pg=sysconf(_SC_PAGESIZE);for(long o=0;o<sz;o+=pg)m[o]=m[o];write(pp[1],"x",1);_exit(0);}
      char x;read(pp[0],&x,1);t[i]=now()-s;waitpid(c,0,0);close(pp[0]);close(pp[1]);}
    qsort(t,N,sizeof(double),cmp);
    printf("fork+touch rss_kb=%ld median_us=%.1f max_us=%.1f\n",kbs[k],t[N/2],t[N-1]);
    munlockall();free(m);}
  return 0;}
