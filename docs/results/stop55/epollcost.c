// Round trip parent -> child -> parent over pipes, both on CPU 0, SCHED_RR (parent 60, child 50).
// The parent waits for the answer by a blocking read, by epoll_wait on an instance that also
// watches 4 idle pipes, by poll on the same 5 pipes, or by
// epoll_wait with a 2 ms timeout (an hrtimer armed and cancelled each wait), then a read. Medians of ROUNDS round
// trips, modes rotated.
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/epoll.h>
#include <poll.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>
#include <signal.h>
static double now(void){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
static int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
static void pin_rr(int prio){cpu_set_t s;CPU_ZERO(&s);CPU_SET(0,&s);sched_setaffinity(0,sizeof s,&s);struct sched_param p={.sched_priority=prio};sched_setscheduler(0,SCHED_RR,&p);}
int main(int argc,char**argv){
  int rounds=argc>1?atoi(argv[1]):100000, reps=argc>2?atoi(argv[2]):6;
  pin_rr(60);
  int to[2],from[2],idle[4][2];pipe(to);pipe(from);for(int i=0;i<4;i++)pipe(idle[i]);
  pid_t c=fork();
  if(!c){pin_rr(50);char b[8];for(;;){if(read(to[0],b,8)!=8)_exit(0);write(from[1],b,8);}}
  int ep=epoll_create1(0);struct epoll_event e={.events=EPOLLIN};
  e.data.fd=from[0];epoll_ctl(ep,EPOLL_CTL_ADD,from[0],&e);
  for(int i=0;i<4;i++){e.data.fd=idle[i][0];epoll_ctl(ep,EPOLL_CTL_ADD,idle[i][0],&e);}
  double*t=malloc(sizeof(double)*rounds);char b[8]="abcdefg";
  struct pollfd pf[5];pf[0].fd=from[0];pf[0].events=POLLIN;
  for(int i=0;i<4;i++){pf[i+1].fd=idle[i][0];pf[i+1].events=POLLIN;}
  const char*name[4]={"read","epoll+read","poll+read","epoll2ms+read"};
  for(int r=0;r<reps;r++)for(int mode=0;mode<4;mode++){
    int m=(mode+r)%4;
    for(int i=0;i<rounds;i++){double t0=now();write(to[1],b,8);
      if(m==1){struct epoll_event ev[8];epoll_wait(ep,ev,8,-1);}
      else if(m==2){poll(pf,5,-1);}
      else if(m==3){struct epoll_event ev[8];epoll_wait(ep,ev,8,2);}
      read(from[0],b,8);t[i]=now()-t0;}
    qsort(t,rounds,sizeof(double),cmp);
    printf("rep %d %-10s median %.2f µs\n",r,name[m],t[rounds/2]);
  }
  kill(c,SIGKILL);waitpid(c,0,0);return 0;}
