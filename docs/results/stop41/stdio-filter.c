// stop 41: a filter that writes through C stdio (fgets/fputs), so the preload library's write() never sees
// its output and it stamps nothing. Measured as /bin/cat under the bench, bind-mounted in a private mount namespace:
// unshare -m sh -c 'mount --bind ./stdio-filter /bin/cat && s3res-bench echo --program preload-lines ...'
#include <stdio.h>
int main(){ static char b[1<<17]; while(fgets(b,sizeof b,stdin)) { fputs(b,stdout); } return 0; }
