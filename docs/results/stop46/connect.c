// Cost in a fork child of joining a Unix stream listener (socket, 2 setsockopt, connect, send)
// against sending on a connection inherited from the parent. Parent on CPU 0, child on CPU 1.
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
static double now(void){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
static void pin(int c){cpu_set_t s;CPU_ZERO(&s);CPU_SET(c,&s);sched_setaffinity(0,sizeof s,&s);}
static int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(int argc,char**argv){
  int N=argc>1?atoi(argv[1]):200;
  struct sockaddr_un a={.sun_family=AF_UNIX};strcpy(a.sun_path,"/tmp/s46/sock");unlink(a.sun_path);
  int l=socket(AF_UNIX,SOCK_STREAM|SOCK_CLOEXEC,0);bind(l,(void*)&a,sizeof a);listen(l,16);
  double *sh=mmap(0,4096,PROT_READ|PROT_WRITE,MAP_SHARED|MAP_ANONYMOUS,-1,0);
  mlockall(MCL_CURRENT|MCL_FUTURE);
  struct sched_param sp={.sched_priority=60};sched_setscheduler(0,SCHED_RR,&sp);
  pin(0);
  double *t[2];t[0]=malloc(8*N);t[1]=malloc(8*N);
  for(int i=0;i<2*N;i++){int mode=i&1;int pre=-1,acc=-1;
    if(mode){pre=socket(AF_UNIX,SOCK_STREAM|SOCK_CLOEXEC,0);connect(pre,(void*)&a,sizeof a);acc=accept4(l,0,0,SOCK_CLOEXEC);}
    pid_t c=fork();
    if(!c){pin(1);double s=now();int fd=pre;
      if(!mode){fd=socket(AF_UNIX,SOCK_STREAM|SOCK_CLOEXEC,0);struct timeval tv={1,0};
        setsockopt(fd,SOL_SOCKET,SO_RCVTIMEO,&tv,sizeof tv);setsockopt(fd,SOL_SOCKET,SO_SNDTIMEO,&tv,sizeof tv);
        connect(fd,(void*)&a,sizeof a);}
      send(fd,"hello123",8,0);sh[0]=now()-s;_exit(0);}
    if(!mode)acc=accept4(l,0,0,SOCK_CLOEXEC);
    char b[8];recv(acc,b,8,MSG_WAITALL);waitpid(c,0,0);t[mode][i/2]=sh[0];close(acc);if(pre>=0)close(pre);usleep(2000);}
  for(int m=0;m<2;m++){qsort(t[m],N,8,cmp);printf("%s median %.1f p90 %.1f us\n",m?"inherited send":"socket+2 setsockopt+connect+send",t[m][N/2],t[m][N*9/10]);}
  return 0;}
