// What the machine gives a 500 Hz loop with no Python in it (tests/bench/bench_servo_loop.py's
// reference row): a SCHED_FIFO thread pinned to one CPU wakes every 2 ms on an absolute schedule
// (clock_nanosleep), records how late it woke, then spins 0.5 ms reading CLOCK_MONOTONIC and
// records every gap in that window: time the thread did not run although it was runnable at the
// highest priority in the guest (interrupts, or the hypervisor descheduling the vCPU).
// usage: vcpu_gaps CPU SECONDS [PRIORITY]
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
static double now(void){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec+t.tv_nsec*1e-9;}
int main(int c,char**v){int cpu=atoi(v[1]);double secs=atof(v[2]);int prio=c>3?atoi(v[3]):90;
 if(cpu>=0){cpu_set_t s;CPU_ZERO(&s);CPU_SET(cpu,&s);sched_setaffinity(0,sizeof s,&s);}
 struct sched_param p={.sched_priority=prio}; if(prio&&sched_setscheduler(0,SCHED_FIFO,&p))perror("fifo");
 struct timespec next; clock_gettime(CLOCK_MONOTONIC,&next);
 double t0=now(),mx=0,wmx=0;long n50=0,n500=0,n3ms=0,w100=0,w500=0,w2ms=0,cycles=0;double tot=0;
 while(now()-t0<secs){
   next.tv_nsec+=2000000; if(next.tv_nsec>=1000000000){next.tv_nsec-=1000000000;next.tv_sec++;}
   clock_nanosleep(CLOCK_MONOTONIC,TIMER_ABSTIME,&next,NULL);
   double due=next.tv_sec+next.tv_nsec*1e-9, w=now()-due; cycles++;
   if(w>100e-6)w100++; if(w>500e-6)w500++; if(w>2e-3)w2ms++; if(w>wmx)wmx=w;
   double last=now(), end=last+0.5e-3;
   while(1){double t=now(); double g=t-last; last=t; if(g>50e-6){n50++;tot+=g;} if(g>500e-6)n500++; if(g>3e-3)n3ms++; if(g>mx)mx=g; if(t>end)break;}
 }
 printf("cpu %d prio %d, %.0f s, %ld cycles: wake late >0.1ms %ld >0.5ms %ld >2ms %ld max %.2f ms | in-spin gaps >50us %ld >0.5ms %ld >3ms %ld max %.2f ms\n",cpu,prio,secs,cycles,w100,w500,w2ms,wmx*1e3,n50,n500,n3ms,mx*1e3);}
