/* What one timer expiry costs the CPU it lands on (results.md, stop 40).
 * A busy loop reads CLOCK_MONOTONIC for one second and counts the gaps between two
 * readings; a timerfd with the given period (µs; 0: none) expires meanwhile, and the loop
 * takes each expiry off it with a non-blocking read (else it would not be re-armed).
 * Build: gcc -O2 timer-expiry.c -o timer-expiry; run: taskset -c 0 ./timer-expiry 100
 */
#include <sys/timerfd.h>
#include <time.h>
#include <stdio.h>
#include <stdint.h>
#include <stdlib.h>
#include <unistd.h>
static uint64_t now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1000000000ull+t.tv_nsec;}
int main(int c,char**v){int per=atoi(v[1]); int fd=timerfd_create(CLOCK_MONOTONIC,TFD_NONBLOCK);
struct itimerspec a={0}; if(per){a.it_value.tv_nsec=per*1000;a.it_interval.tv_nsec=per*1000;} timerfd_settime(fd,0,&a,0);
uint64_t end=now()+1000000000ull, last=now(); long gaps[6]={0}; uint64_t it=0,exp=0; char b[8];
while(1){uint64_t n=now(); if(n>end)break; uint64_t d=n-last; last=n; it++;
 if(d>3000){ if(d<5000)gaps[0]++; else if(d<10000)gaps[1]++; else if(d<20000)gaps[2]++; else if(d<40000)gaps[3]++; else gaps[4]++;}
 if(read(fd,b,8)==8)exp++;}
printf("period %d us: iters %lu expiries %lu gaps 3-5us %ld 5-10 %ld 10-20 %ld 20-40 %ld >40 %ld\n",per,it,exp,gaps[0],gaps[1],gaps[2],gaps[3],gaps[4]);}
