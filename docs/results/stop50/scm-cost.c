#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <time.h>
#include <sys/socket.h>
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e6+t.tv_nsec/1e3;}
int cmp(const void*a,const void*b){double x=*(double*)a,y=*(double*)b;return x<y?-1:x>y;}
int main(int argc,char**argv){
  int nfd=atoi(argv[1]); int sv[2]; socketpair(AF_UNIX,SOCK_STREAM,0,sv);
  int N=2000; double t[N], tc[N];
  for(int i=0;i<N;i++){
    int fds[8]; for(int k=0;k<nfd;k+=2){int p[2]; pipe(p); fds[k]=p[0]; fds[k+1]=p[1];}
    char buf[CMSG_SPACE(sizeof(int)*8)]; struct iovec io={.iov_base="x",.iov_len=1};
    struct msghdr m={.msg_iov=&io,.msg_iovlen=1,.msg_control=buf,.msg_controllen=CMSG_SPACE(sizeof(int)*nfd)};
    struct cmsghdr*c=CMSG_FIRSTHDR(&m); c->cmsg_level=SOL_SOCKET; c->cmsg_type=SCM_RIGHTS; c->cmsg_len=CMSG_LEN(sizeof(int)*nfd); memcpy(CMSG_DATA(c),fds,sizeof(int)*nfd);
    double s=now(); sendmsg(sv[0],&m,0); tc[i]=now()-s;
    for(int k=0;k<nfd;k++) close(fds[k]);
    char b2[CMSG_SPACE(sizeof(int)*8)]; char x; struct iovec io2={.iov_base=&x,.iov_len=1};
    struct msghdr m2={.msg_iov=&io2,.msg_iovlen=1,.msg_control=b2,.msg_controllen=sizeof b2};
    s=now(); recvmsg(sv[1],&m2,MSG_CMSG_CLOEXEC); t[i]=now()-s;
    struct cmsghdr*c2=CMSG_FIRSTHDR(&m2); int*got=(int*)CMSG_DATA(c2); for(int k=0;k<nfd;k++) close(got[k]);
  }
  qsort(t,N,sizeof(double),cmp); qsort(tc,N,sizeof(double),cmp);
  printf("%d fds: sendmsg median %.2f us, recvmsg median %.2f us\n",nfd,tc[N/2],t[N/2]);
}
