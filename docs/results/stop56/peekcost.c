#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <fcntl.h>
#include <sys/ioctl.h>
#include <time.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e9+t.tv_nsec;}
int main(int argc,char**argv){
  int n=atoi(argv[1]); int N=200000;
  int c[2],p[2]; pipe(c); pipe(p); fcntl(p[1],F_SETFL,O_NONBLOCK);
  char *buf=calloc(1,1<<20), *dec=calloc(1,1<<20), *log=calloc(1,1<<20);
  for(int mode=0;mode<2;mode++){
   for(int rep=0;rep<3;rep++){
    double total=0;
    for(int i=0;i<N;i++){
      write(c[1],buf,n);
      double s=now();
      if(mode==0){ ssize_t k=tee(c[0],p[1],1<<16,SPLICE_F_NONBLOCK); read(p[0],dec,k); read(c[0],log,k);}
      else { int avail=0; ioctl(c[0],FIONREAD,&avail); read(c[0],log,avail); memcpy(dec,log,avail);}
      total+=now()-s;
    }
    printf("%s n=%d: %.0f ns per take\n", mode?"fionread+read+memcpy":"tee+read+read", n, total/N);
   }
  }
}
