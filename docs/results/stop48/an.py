import json,sys,statistics as st,random
from collections import defaultdict
d=defaultdict(lambda: defaultdict(dict))
for line in open(sys.argv[1]):
    v,rep,js=line.split(' ',2); j=json.loads(js)
    d[j['size']][v][int(rep)]=(j['median_us'],j['extra']['in_service_median_us'])
vs=sys.argv[2:]
for size in sorted(d):
    a,b=vs
    reps=sorted(set(d[size][a])&set(d[size][b]))
    ra=[d[size][b][r][0]/d[size][a][r][0] for r in reps]
    rs=[d[size][b][r][1]/d[size][a][r][1] for r in reps]
    random.seed(1)
    def ci(x):
        bs=sorted(st.median(random.choices(x,k=len(x))) for _ in range(2000)); return bs[50],bs[1949]
    print(f"{size//1024} KiB, {len(reps)} pairs: {a} {st.median(d[size][a][r][0] for r in reps):.1f} -> {b} {st.median(d[size][b][r][0] for r in reps):.1f} µs; ratio {st.median(ra):.3f} {ci(ra)}, lower in {sum(x<1 for x in ra)}")
    print(f"   in service: {st.median(d[size][a][r][1] for r in reps):.1f} -> {st.median(d[size][b][r][1] for r in reps):.1f}; ratio {st.median(rs):.3f} {ci(rs)}")
