// stop 42: what a fork child's relock costs, and of what.
// gcc -O2 -o relock relock.c && taskset -c 1 chrt -r 50 ./relock MODE KIB
// MODE a: mlockall(CURRENT|ONFAULT) then mlockall(FUTURE)  (replica-rt today)
//      b: mlock2(ONFAULT) of each private writable mapping (snapshot taken before fork), then mlockall(FUTURE)
//      c: open+close /proc/self/maps
//      d: mlockall(CURRENT|FUTURE|ONFAULT) in one call
//      e: b, then (timed separately) mlockall(CURRENT|FUTURE|ONFAULT) for the rest
//      f: madvise(MADV_POPULATE_WRITE) of each private writable mapping, whole
//      g: a, then f;  h: f, then b;  i: f, then a
//      j: open+close /proc/self/maps twice, the second timed apart;  k: /proc/self/stat;  l: /dev/null;  m: getppid
// (docs/results.md, stop 42). The parent lists its rw-p mappings (stdio) before each fork.
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <time.h>
#include <string.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
static unsigned long rs[256], re[256]; static int nr;
static void snap(){ FILE*f=fopen("/proc/self/maps","r"); char l[512]; nr=0;
  while(fgets(l,sizeof l,f)){unsigned long a,b; char p[5]; if(sscanf(l,"%lx-%lx %4s",&a,&b,p)==3 && p[0]=='r'&&p[1]=='w'&&p[3]=='p' && !strstr(l,"[v")) {rs[nr]=a;re[nr]=b;nr++;}}
  fclose(f);}
static int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(int argc,char**argv){
  char mode=argv[1][0]; size_t sz=atol(argv[2])*1024; int n=200;
  mlockall(MCL_CURRENT|MCL_FUTURE);
  char *m=malloc(sz); memset(m,1,sz);
  double *t=calloc(n,sizeof(double)), *t2=calloc(n,sizeof(double));
  snap();
  for(int i=0;i<n;i++){
    int p[2]; pipe(p); snap();
    pid_t c=fork();
    if(!c){ double d[2]={0,0}; double s=now();
      if(mode=='a'){ mlockall(MCL_CURRENT|MCL_ONFAULT); mlockall(MCL_FUTURE); }
      if(mode=='b'||mode=='e'){ for(int k=0;k<nr;k++) mlock2((void*)rs[k],re[k]-rs[k],MLOCK_ONFAULT); mlockall(MCL_FUTURE);}
      if(mode=='c'){ int fd=open("/proc/self/maps",O_RDONLY|O_CLOEXEC); close(fd);}
      if(mode=='d'){ mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT);}
      if(mode=='f'){ for(int k=0;k<nr;k++) madvise((void*)rs[k],re[k]-rs[k],MADV_POPULATE_WRITE);}
      if(mode=='g'){ mlockall(MCL_CURRENT|MCL_ONFAULT); mlockall(MCL_FUTURE); for(int k=0;k<nr;k++) madvise((void*)rs[k],re[k]-rs[k],MADV_POPULATE_WRITE);}
      if(mode=='h'){ for(int k=0;k<nr;k++) madvise((void*)rs[k],re[k]-rs[k],MADV_POPULATE_WRITE); for(int k=0;k<nr;k++) mlock2((void*)rs[k],re[k]-rs[k],MLOCK_ONFAULT); mlockall(MCL_FUTURE);}
      if(mode=='i'){ for(int k=0;k<nr;k++) madvise((void*)rs[k],re[k]-rs[k],MADV_POPULATE_WRITE); mlockall(MCL_CURRENT|MCL_ONFAULT); mlockall(MCL_FUTURE);}
      if(mode=='j'){ int fd=open("/proc/self/maps",O_RDONLY|O_CLOEXEC); close(fd); double s2=now(); fd=open("/proc/self/maps",O_RDONLY|O_CLOEXEC); close(fd); d[1]=now()-s2; }
      if(mode=='k'){ int fd=open("/proc/self/stat",O_RDONLY|O_CLOEXEC); close(fd);}
      if(mode=='l'){ int fd=open("/dev/null",O_RDONLY|O_CLOEXEC); close(fd);}
      if(mode=='m'){ getppid(); }
      double e=now(); d[0]=e-s;
      if(mode=='e'){ mlockall(MCL_CURRENT|MCL_FUTURE|MCL_ONFAULT); d[1]=now()-e; }
      write(p[1],d,sizeof d); _exit(0);}
    double d[2]; read(p[0],d,sizeof d); t[i]=d[0]; t2[i]=d[1]; waitpid(c,0,0); close(p[0]); close(p[1]);
    usleep(2000);
  }
  qsort(t,n,sizeof(double),cmp); qsort(t2,n,sizeof(double),cmp);
  printf("mode %c size %zuK rw-p %d: median %.1f us p90 %.1f | second part median %.1f p90 %.1f\n", mode, sz/1024, nr, t[n/2], t[n*9/10], t2[n/2], t2[n*9/10]);
}
