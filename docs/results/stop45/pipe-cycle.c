// One voter's forwarding of a frame to three replicas, in one process, timed: the frame is
// written into an input pipe, forwarded into three pipes (write, or tee from the input), then
// taken off the input and read from the three. Stop 45 (docs/results.md): tee makes the three
// forwards faster and the whole cycle slower, the shared pages being freed instead of kept as
// each pipe's spare page.  gcc -O2 -o pipe-cycle pipe-cycle.c && taskset -c 1 ./pipe-cycle
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#include <fcntl.h>
#include <time.h>
#include <sys/uio.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
static int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(){
  char *buf=aligned_alloc(4096,4*4096); char*b=buf+60; char*r=buf+2*4096+60;
  int in[2],out[3][2]; pipe(in); for(int i=0;i<3;i++)pipe(out[i]);
  int N=20000; double *t=malloc(N*sizeof(double)),*tf=malloc(N*sizeof(double));
  int sizes[]={12,4100};
  for(int rep=0;rep<3;rep++) for(int si=0;si<2;si++) for(int mode=0;mode<2;mode++){int n=sizes[si];
    for(int i=0;i<N;i++){
      double s=now();
      write(in[1],b,n);
      double f0=now();
      for(int k=0;k<3;k++){ if(mode==0) write(out[k][1],b,n); else { if(tee(in[0],out[k][1],n,SPLICE_F_NONBLOCK)!=n){perror("tee");exit(1);} } }
      tf[i]=now()-f0;
      read(in[0],r,n); for(int k=0;k<3;k++){int g=0;while(g<n)g+=read(out[k][0],r+g,n-g);}
      t[i]=now()-s;
    }
    qsort(t,N,sizeof(double),cmp); qsort(tf,N,sizeof(double),cmp); printf("%5d %s: whole cycle median %.3f us, the 3 forwards %.3f\n",n,mode?"tee  ":"write",t[N/2],tf[N/2]);}
}
